"""nerfstudio's ``Trainer`` made to survive long runs: a non-finite guard and atomic checkpoints.

Why: a run of the paper's size takes days. A single NaN (fp16 overflow, a bad batch) handed to
Adam poisons every parameter and the moments for good, and the next periodic checkpoint then
overwrites the last good one with NaNs. A kill (power cut, pre-empted cloud GPU, OOM killer)
in the middle of ``torch.save`` leaves a truncated ``step-*.ckpt`` that nerfstudio's
``--load-dir`` picks as the newest and fails to load. This module fixes both by subclassing
nerfstudio, without changing its training loop or its checkpoint format:

* **Non-finite guard.** Every optimiser step is checked before it is taken: the total loss (seen
  as it passes through the gradient scaler) and the gradients of every parameter group that is
  about to step. If anything is NaN or inf, no optimiser and no scheduler steps (the parameters,
  Adam's moments and the learning rates stay exactly as after the last good step) and one warning
  names the step, the non-finite loss terms and parameter groups. Under ``torch.distributed``
  the decision is agreed between all ranks, so they skip together and stay identical. After
  ``guard.max_consecutive_bad_steps`` bad steps in a row training stops with
  :class:`NonFiniteTrainingError`; the last good checkpoint is left in place.
* **Loss spikes.** A step whose total loss is above ``guard.loss_spike_ratio`` times the median of
  the last ``LOSS_SPIKE_WINDOW`` steps' is skipped the same way. One batch that dominates the
  gradient fills both of Adam's moments: the step is then about ``0.1 / sqrt(0.001)`` ≈ 3 learning
  rates on every parameter in the sign of that batch's gradient, decaying by 0.9 a step for some 20
  steps, where ordinary batches, whose gradients partly cancel, move a parameter far less. Measured
  on a path-traced coastal scene: a lone SfM depth 34% behind the surface (DS-NeRF pulls on it with
  ``1/w``) made one batch's loss 100× the median at step 1477 of 1500, and the surfaces' opacity fell
  0.77 → 0.39 in 20 steps. The median window holds skipped steps too, so a lasting change of the
  loss's level is followed after half a window.
* **Checkpoints.** A checkpoint is written by nerfstudio's own ``save_checkpoint`` into a staging
  folder next to the checkpoint folder, flushed to disk, then moved into place with
  ``os.replace`` (atomic on POSIX and Windows): the checkpoint folder only ever holds complete
  files. A state with any non-finite tensor is never written.
* **Resume.** ``--load-dir``/``--load-checkpoint`` are nerfstudio's; we add a clear error when
  the folder holds no checkpoint, and (``total_iterations_on_resume``, on by default) a resumed
  run stops at ``max_num_iterations`` in total, where the killed run would have stopped, instead
  of training ``max_num_iterations`` more.
* **Bad input.** An :class:`~seathru_nerfstudio.input_errors.InputError` met while the trainer
  sets up or trains (the dataparser's checks, the model's option checks, a data-loading worker
  that met a bad file) ends ``ns-train`` with its one line and exit status 1, no traceback. A
  checkpoint folder without checkpoints is refused when it is named, whoever names it: ``ns-train
  --load-dir``, or ``ns-eval``/``ns-render``/``ns-viewer``, which point ``load_dir`` at the run's
  ``nerfstudio_models/`` (nerfstudio itself would fail there with ``IndexError``).
"""

from __future__ import annotations

import contextlib
import math
import os
import statistics
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Type

import torch
import torch.distributed as dist

from nerfstudio.configs.base_config import PrintableConfig
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.trainer import TRAIN_INTERATION_OUTPUT, Trainer, TrainerConfig
from nerfstudio.utils import comms
from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio import compat, medium_report
from seathru_nerfstudio.data.datamanager import DataWorkerKilled
from seathru_nerfstudio.input_errors import InputError, exit_on_input_error

CHECKPOINT_GLOB = "step-*.ckpt"
LOSS_SPIKE_WINDOW = 20
"""Steps whose total losses' median a spike is measured against."""


class NonFiniteTrainingError(RuntimeError):
    """Training produced non-finite values it cannot recover from (see the message)."""


@dataclass
class NonFiniteGuardConfig(PrintableConfig):
    """The non-finite guard (``--guard.enabled``, ``--guard.max-consecutive-bad-steps``)."""

    enabled: bool = True
    """Skip optimiser steps whose loss or gradients are NaN/inf. Off: nerfstudio's plain behaviour."""
    max_consecutive_bad_steps: int = 20
    """Stop training after this many skipped steps in a row: the run has diverged, not hiccupped."""
    loss_spike_ratio: float = 10.0
    """Also skip a step whose loss is above this many times the median of the last 20 steps; 0: off."""


@dataclass
class SeathruTrainerConfig(TrainerConfig):
    """nerfstudio's ``TrainerConfig`` with the non-finite guard and crash-safe checkpoints."""

    _target: Type = field(default_factory=lambda: SeathruTrainer)
    guard: NonFiniteGuardConfig = field(default_factory=NonFiniteGuardConfig)
    """Non-finite loss/gradient guard."""
    total_iterations_on_resume: bool = True
    """When resuming (--load-dir/--load-checkpoint), stop at max_num_iterations in total, where the
    interrupted run would have stopped. False: nerfstudio's behaviour, max_num_iterations more."""

    def __setattr__(self, name: str, value) -> None:
        if name == "load_dir" and value is not None:
            with exit_on_input_error():  # no code of ours is above ns-eval's eval_setup, which sets it
                check_checkpoint_folder(Path(value), getattr(self, "load_step", None))
        super().__setattr__(name, value)


def check_checkpoint_folder(load_dir: Path, load_step: Optional[int] = None) -> None:
    """Raise :class:`InputError` unless ``load_dir`` is a folder that holds a checkpoint (the one of
    ``load_step``, if given)."""
    if not load_dir.is_dir():
        raise InputError(
            f"checkpoint folder {load_dir} does not exist: point --load-dir (or --load-config) at a run whose "
            "nerfstudio_models/ holds step-*.ckpt files"
        )
    wanted = f"step-{load_step:09d}.ckpt" if load_step is not None else CHECKPOINT_GLOB
    if not list(load_dir.glob(wanted)):
        raise InputError(
            f"checkpoint folder {load_dir} holds no {wanted}: the run stopped before its first save (see "
            "--steps-per-save), or its checkpoints were deleted. Train again, or use a run that saved one"
        )


def _nonfinite_tensors(named: Iterable) -> List[str]:
    """Names of the floating-point tensors in ``named`` ((name, value) pairs, nested dicts and
    lists walked) that hold a NaN or an inf."""
    bad: List[str] = []
    stack = list(named)
    while stack:
        name, value = stack.pop()
        if isinstance(value, torch.Tensor):
            if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                bad.append(name)
        elif isinstance(value, dict):
            stack.extend((f"{name}.{k}", v) for k, v in value.items())
        elif isinstance(value, (list, tuple)):
            stack.extend((f"{name}[{i}]", v) for i, v in enumerate(value))
        elif isinstance(value, float) and not torch.isfinite(torch.tensor(value)):
            bad.append(name)
    return sorted(bad)


class NonFiniteGuard:
    """The state of the guard for one trainer: what the current step saw, and the bad-step run.

    The checks are split across the two objects nerfstudio's ``train_iteration`` hands the loss
    and the gradients to before the optimiser steps (:class:`GuardedGradScaler` and
    :class:`GuardedOptimizers`), so nerfstudio's training step itself is used unchanged."""

    def __init__(self, config: NonFiniteGuardConfig, world_size: int = 1):
        if config.max_consecutive_bad_steps < 1:
            raise ValueError(f"guard.max_consecutive_bad_steps must be >= 1, got {config.max_consecutive_bad_steps}")
        if not config.loss_spike_ratio == 0 and not config.loss_spike_ratio > 1:
            raise ValueError(f"guard.loss_spike_ratio must be 0 (off) or > 1, got {config.loss_spike_ratio}")
        self.config = config
        self.world_size = world_size
        self.consecutive_bad_steps = 0
        self.skipped_steps: List[int] = []
        self.spike_skipped_steps: List[int] = []
        self.recent_losses: deque = deque(maxlen=LOSS_SPIKE_WINDOW)
        self._loss: Optional[torch.Tensor] = None
        self._spike_limit: Optional[float] = None
        self._spike = False
        self._loss_finite: Optional[torch.Tensor] = None
        self._bad_groups: List[str] = []
        self._decided = False
        self.skip = False
        self._only_elsewhere = False

    def start_step(self) -> None:
        self._loss = None
        self._spike = False
        self._loss_finite = None
        self._bad_groups = []
        self._decided = False
        self.skip = False
        self._only_elsewhere = False

    def record_loss(self, loss: torch.Tensor) -> None:
        """Called with the total loss before backward (no host sync here)."""
        self._loss = loss.detach()
        self._loss_finite = torch.isfinite(self._loss).all()

    def decide(self, parameters: Dict[str, List[torch.nn.Parameter]], groups: List[str]) -> bool:
        """Whether the optimiser step of ``groups`` must be skipped. One host sync, and under
        ``torch.distributed`` one all-reduce of a fixed-size flag vector (one flag per group, one
        for the loss), so every rank takes the same decision."""
        device = self._loss_finite.device if self._loss_finite is not None else None
        flags = []
        for group in groups:
            grads = [p.grad for p in parameters[group] if p.grad is not None]
            if device is None and grads:
                device = grads[0].device
            # one pass per tensor, no temporaries: a sum is NaN/inf iff an element is, or if finite
            # gradients add up beyond 3e38 (|g| ~ 1e38 / size: a run that has diverged anyway)
            flags.append(torch.isfinite(torch.stack([g.sum() for g in grads])).all() if grads else None)
        flags.append(self._loss_finite)
        self._spike_limit = None
        median = statistics.median(self.recent_losses) if len(self.recent_losses) == LOSS_SPIKE_WINDOW else 0.0
        spike_free = None  # one flag on every rank, checked or not, so the all-reduce has one size
        if self.config.loss_spike_ratio > 0 and median > 0 and self._loss is not None:  # a ratio needs a positive level
            self._spike_limit = self.config.loss_spike_ratio * median
            spike_free = (self._loss <= self._spike_limit).all()
        flags.append(spike_free)
        local = torch.stack([torch.ones((), dtype=torch.bool, device=device) if f is None else f.to(device) for f in flags])
        local = local.to(torch.int32)
        combined = local
        if self.world_size > 1 and dist.is_available() and dist.is_initialized():
            combined = local.clone()
            dist.all_reduce(combined, op=dist.ReduceOp.MIN)
        local_ok, combined_ok = local.tolist(), combined.tolist()
        self._bad_groups = [g for g, ok in zip(groups, local_ok) if not ok]
        self.skip = not all(combined_ok)
        finite_elsewhere = all(combined_ok[: len(groups) + 1])
        self._spike = self.skip and finite_elsewhere  # every rank finite: a loss spike on some rank
        self._only_elsewhere = self.skip and all(local_ok)
        self._decided = True
        return self.skip

    def finish_step(self, step: int, loss_dict: Dict[str, torch.Tensor], last_checkpoint: Optional[Path]) -> None:
        """Warn about a skipped step and stop after too many in a row."""
        loss = float(self._loss) if self._loss is not None and self._loss.numel() == 1 else float("nan")
        if math.isfinite(loss):
            self.recent_losses.append(loss)  # skipped or not: a lasting change of level is followed
        if not self._decided:
            # no parameter group stepped (gradient accumulation): a non-finite loss has poisoned
            # the accumulated gradients, and the step that uses them is the one skipped
            return
        if self._spike:
            self.spike_skipped_steps.append(step)
            where = "" if loss <= (self._spike_limit or float("inf")) else f"loss {loss:.4g}, "
            rank = f"rank {comms.get_rank()}: " if self.world_size > 1 else ""
            CONSOLE.print(
                f"[yellow]{rank}step {step}: optimiser step skipped, {where}a loss spike (above "
                f"{self.config.loss_spike_ratio:g}× the median of the last {LOSS_SPIKE_WINDOW} steps"
                f"{'' if where else ', on another rank'})",
                soft_wrap=True,
            )
            return
        if not self.skip:
            self.consecutive_bad_steps = 0
            return
        self.consecutive_bad_steps += 1
        self.skipped_steps.append(step)
        limit = self.config.max_consecutive_bad_steps
        bad_losses = [k for k, v in loss_dict.items() if not bool(torch.isfinite(torch.as_tensor(v)).all())]
        what = []
        if bad_losses:
            what.append("non-finite loss " + ", ".join(repr(k) for k in bad_losses))
        if self._bad_groups:
            what.append("non-finite gradients in parameter group " + ", ".join(repr(g) for g in self._bad_groups))
        if self._only_elsewhere:
            what.append("non-finite values on another rank")
        if not what:
            what.append("non-finite total loss")
        rank = f"rank {comms.get_rank()}: " if self.world_size > 1 else ""
        if what != ["non-finite values on another rank"] or comms.is_main_process():
            CONSOLE.print(
                f"[bold yellow]{rank}step {step}: optimiser step skipped, {'; '.join(what)} "
                f"({self.consecutive_bad_steps}/{limit} bad steps in a row)",
                soft_wrap=True,  # one line, whatever the terminal width: easy to grep in a log
            )
        if self.consecutive_bad_steps >= limit:
            where = (
                f"The last good checkpoint is {last_checkpoint}; resume from it with --load-dir {last_checkpoint.parent}"
                if last_checkpoint is not None
                else "No checkpoint was written before this happened"
            )
            raise NonFiniteTrainingError(
                f"Training stopped at step {step}: {limit} optimiser steps in a row had a non-finite loss or "
                f"gradient (last: {'; '.join(what)}). The parameters are those after the last good step. {where}. "
                "Likely causes: a learning rate too high, fp16 overflow (try --mixed-precision False), or bad input data."
            )


class GuardedGradScaler(torch.amp.GradScaler):
    """nerfstudio's gradient scaler, which also shows the guard the total loss before backward."""

    def __init__(self, guard: NonFiniteGuard, **kwargs):
        super().__init__("cuda", **kwargs)  # "cuda": the device nerfstudio's own scaler uses
        self.guard = guard

    def scale(self, outputs):  # type: ignore[override]
        if isinstance(outputs, torch.Tensor):
            self.guard.record_loss(outputs)
        return super().scale(outputs)


class GuardedOptimizers(Optimizers):
    """nerfstudio's optimizers; the step (and the scheduler step) is skipped when the guard says so."""

    def __init__(self, config: Dict, param_groups: Dict[str, List[torch.nn.Parameter]], guard: NonFiniteGuard):
        super().__init__(config, param_groups)
        self.guard = guard

    def optimizer_scaler_step_some(self, grad_scaler, param_groups: List[str]) -> None:
        if not self.guard.decide(self.parameters, param_groups):
            return super().optimizer_scaler_step_some(grad_scaler, param_groups)
        if grad_scaler.is_enabled():
            # let the mixed-precision scaler see the overflow (it lowers its scale at update())
            for group in param_groups:
                if any(p.grad is not None for p in self.parameters[group]):
                    grad_scaler.unscale_(self.optimizers[group])

    def optimizer_scaler_step_all(self, grad_scaler) -> None:
        self.optimizer_scaler_step_some(grad_scaler, list(self.optimizers.keys()))

    def scheduler_step_all(self, step: int) -> None:
        if not self.guard.skip:  # the learning rate follows the steps actually taken
            super().scheduler_step_all(step)


class SeathruTrainer(Trainer):
    """nerfstudio's ``Trainer`` with the non-finite guard, atomic checkpoints and clear resume errors."""

    config: SeathruTrainerConfig

    def __init__(self, config: SeathruTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        with exit_on_input_error():
            super().__init__(config, local_rank, world_size)
        guard_config = getattr(config, "guard", NonFiniteGuardConfig())
        self.guard: Optional[NonFiniteGuard] = None
        if guard_config.enabled:
            self.guard = NonFiniteGuard(guard_config, world_size)
            self.grad_scaler = GuardedGradScaler(self.guard, enabled=self.grad_scaler.is_enabled())

    def setup(self, test_mode="val") -> None:
        """nerfstudio's set-up (data, model, checkpoint); bad input ends it with one line (exit status 1)."""
        with exit_on_input_error():
            super().setup(test_mode)

    def train(self) -> None:
        """nerfstudio's training loop; bad input met on the way (by the data-loading worker), or a
        worker killed by the system, ends it with one line."""
        with exit_on_input_error(DataWorkerKilled):
            super().train()

    # ---------------------------------------------------------------- guard
    def setup_optimizers(self) -> Optimizers:
        if self.guard is None:
            return super().setup_optimizers()
        return GuardedOptimizers(self.config.optimizers.copy(), self.pipeline.get_param_groups(), self.guard)

    def train_iteration(self, step: int) -> TRAIN_INTERATION_OUTPUT:
        if self.guard is None:
            return super().train_iteration(step)
        self.guard.start_step()
        loss, loss_dict, metrics_dict = super().train_iteration(step)
        self.guard.finish_step(step, loss_dict, self.latest_checkpoint())
        return loss, loss_dict, metrics_dict

    # ---------------------------------------------------------- checkpoints
    @property
    def staging_dir(self) -> Path:
        """Where a checkpoint is written before it is moved into place: a sibling of the
        checkpoint folder (same file system, so the move is atomic; not inside it, because
        nerfstudio's ``--load-dir`` reads every name in that folder as a step number)."""
        return self.checkpoint_dir.parent / f".{self.checkpoint_dir.name}.partial"

    def latest_checkpoint(self) -> Optional[Path]:
        found = sorted(self.checkpoint_dir.glob(CHECKPOINT_GLOB)) if self.checkpoint_dir.exists() else []
        return found[-1] if found else None

    def _check_state_is_finite(self, step: int) -> None:
        model = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        bad = _nonfinite_tensors(("pipeline." + k, v) for k, v in model.state_dict().items())
        bad += _nonfinite_tensors((f"optimizers.{k}", o.state_dict()["state"]) for k, o in self.optimizers.optimizers.items())
        if bad:
            shown = ", ".join(bad[:8]) + (f" and {len(bad) - 8} more" if len(bad) > 8 else "")
            raise NonFiniteTrainingError(
                f"Refusing to write the checkpoint of step {step}: non-finite values in {shown}. "
                f"The last good checkpoint ({self.latest_checkpoint() or 'none yet'}) is left as it is."
            )

    def save_checkpoint(self, step: int) -> None:
        """Check the state (on every rank, so all stop together), then, on rank 0 only, write
        with nerfstudio's ``save_checkpoint`` into the staging folder and move the file into place."""
        self._check_state_is_finite(step)
        if not comms.is_main_process():
            return
        final_dir, staging = self.checkpoint_dir, self.staging_dir
        staging.mkdir(parents=True, exist_ok=True)
        for leftover in staging.glob("*"):  # from a run killed while saving
            leftover.unlink()
        self.checkpoint_dir = staging
        try:
            super().save_checkpoint(step)
        finally:
            self.checkpoint_dir = final_dir
        written = list(staging.glob(CHECKPOINT_GLOB))
        if len(written) != 1:
            raise RuntimeError(f"expected nerfstudio to write one checkpoint in {staging}, found {written}")
        (tmp,) = written
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())  # the bytes are on disk before the name points to them
        final_dir.mkdir(parents=True, exist_ok=True)
        target = final_dir / tmp.name
        os.replace(tmp, target)
        with contextlib.suppress(OSError):  # empty now: a finished run leaves no staging folder behind
            staging.rmdir()
        _fsync_dir(final_dir)
        if self.config.save_only_latest_checkpoint:
            for old in final_dir.glob(CHECKPOINT_GLOB):
                if old != target:
                    old.unlink()
        medium_report.write_for_pipeline(self.pipeline, self.base_dir / medium_report.REPORT_NAME, step)  # beside config.yml

    def _load_checkpoint(self) -> None:
        load_dir = self.config.load_dir
        if load_dir is not None:
            check_checkpoint_folder(Path(load_dir), self.config.load_step)
        compat.allow_nerfstudio_checkpoints()  # nerfstudio's torch.load(weights_only=True) reads NumPy scalars
        super()._load_checkpoint()
        if load_dir is None and self.config.load_checkpoint is None:
            return
        self.step = self._start_step - 1  # the loaded step: what _after_train saves if no step is left
        if self.config.total_iterations_on_resume:
            self.config.max_num_iterations = max(0, self.config.max_num_iterations - self._start_step)
            CONSOLE.print(
                f"Resuming at step {self._start_step}: {self.config.max_num_iterations} iterations left "
                f"(--total-iterations-on-resume False trains max_num_iterations more instead)."
            )


def _fsync_dir(path: Path) -> None:
    """Make a rename durable (POSIX); a no-op where folders cannot be opened (Windows)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)

