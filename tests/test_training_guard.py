"""The non-finite guard and the checkpoint writer of ``SeathruTrainer`` (issue 11), with real
nerfstudio trainers of a tiny ``seathru-nerf-lite`` on a tiny scene.

NaNs are injected with a forward hook on the object field's colour head, at chosen steps."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Dict, List
from unittest import mock

import pytest
import torch

from tiny_training import make_scene, tiny_config

from seathru_nerfstudio.compat import load_checkpoint
from seathru_nerfstudio.training import GuardedGradScaler, NonFiniteTrainingError, SeathruTrainer

pytestmark = pytest.mark.slow  # trains through nerfstudio's Trainer


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return make_scene(tmp_path_factory.mktemp("guard"))


def make_trainer(scene: Path, out: Path, iterations: int, **fields) -> SeathruTrainer:
    torch.manual_seed(0)
    config = tiny_config(scene, out, iterations, **fields)
    trainer = config.setup(local_rank=0, world_size=1)
    assert isinstance(trainer, SeathruTrainer), "seathru-nerf-lite must use SeathruTrainer"
    trainer.setup()
    return trainer


def inject_nan(trainer: SeathruTrainer, when: Callable[[int], bool]) -> None:
    """NaN colours from the object field in the training steps where ``when(step)``."""

    def hook(module, inputs, output):
        if module.training and when(trainer.step):
            return output * float("nan")
        return None

    trainer.pipeline.model.field.mlp_head.register_forward_hook(hook)


def snapshot_each_step(trainer: SeathruTrainer) -> Dict[int, Dict[str, torch.Tensor]]:
    """The parameters as each training step starts (its first forward pass)."""
    seen: Dict[int, Dict[str, torch.Tensor]] = {}

    def pre_hook(module, inputs):
        if module.training and trainer.step not in seen:
            seen[trainer.step] = {k: v.detach().clone() for k, v in module.named_parameters()}

    trainer.pipeline.model.register_forward_pre_hook(pre_hook)
    return seen


def assert_all_finite(state, where: str = "") -> None:
    if isinstance(state, torch.Tensor):
        if state.is_floating_point():
            assert torch.isfinite(state).all(), f"non-finite tensor at {where}"
    elif isinstance(state, dict):
        for k, v in state.items():
            assert_all_finite(v, f"{where}.{k}")
    elif isinstance(state, (list, tuple)):
        for i, v in enumerate(state):
            assert_all_finite(v, f"{where}[{i}]")


def checkpoints(trainer: SeathruTrainer) -> List[Path]:
    return sorted(trainer.checkpoint_dir.glob("step-*.ckpt"))


def test_a_single_nan_step_is_skipped_with_one_warning_and_training_goes_on(scene, tmp_path, capsys):
    iterations, bad = 8, 3
    trainer = make_trainer(scene, tmp_path, iterations)
    inject_nan(trainer, lambda step: step == bad)
    params = snapshot_each_step(trainer)
    trainer.train()

    out = capsys.readouterr().out
    warnings = [line for line in out.splitlines() if "optimiser step skipped" in line]
    assert len(warnings) == 1, out[-3000:]
    assert f"step {bad}:" in warnings[0] and "'rgb_loss'" in warnings[0] and "'fields'" in warnings[0]
    assert trainer.guard.skipped_steps == [bad]

    # the skipped step changed nothing; the steps around it did
    for name, value in params[bad].items():
        assert torch.equal(value, params[bad + 1][name]), f"{name} changed in the skipped step"
    assert any(not torch.equal(v, params[bad + 1][k]) for k, v in params[bad + 2].items())

    (ckpt,) = checkpoints(trainer)
    state = load_checkpoint(ckpt)
    assert state["step"] == iterations - 1
    assert_all_finite(state["pipeline"], "pipeline")
    assert_all_finite(state["optimizers"], "optimizers")
    # Adam and the learning-rate schedule followed the steps actually taken
    adam_steps = {float(s["step"]) for s in state["optimizers"]["fields"]["state"].values()}
    assert adam_steps == {iterations - 1.0}
    assert state["schedulers"]["fields"]["last_epoch"] == iterations - 1


def test_repeated_nans_stop_training_and_the_last_good_checkpoint_loads_and_renders(scene, tmp_path, capsys):
    trainer = make_trainer(scene, tmp_path, 30, steps_per_save=4)
    trainer.config.guard.max_consecutive_bad_steps = 3
    first_bad = 6
    inject_nan(trainer, lambda step: step >= first_bad)
    with pytest.raises(NonFiniteTrainingError) as raised:
        trainer.train()
    message = str(raised.value)
    assert f"stopped at step {first_bad + 2}" in message and "3 optimiser steps in a row" in message, message
    (ckpt,) = checkpoints(trainer)
    assert ckpt.name == "step-000000004.ckpt" and str(ckpt) in message, message
    assert trainer.guard.skipped_steps == [6, 7, 8]
    assert capsys.readouterr().out.count("optimiser step skipped") == 3

    state = load_checkpoint(ckpt)
    assert_all_finite(state, "checkpoint")

    resumed = make_trainer(scene, tmp_path / "resumed", 6, load_dir=ckpt.parent)
    assert resumed._start_step == 5
    model = resumed.pipeline.model
    for key, value in state["pipeline"].items():
        if key.startswith("_model."):
            assert torch.equal(model.state_dict()[key[len("_model.") :]], value), key
    camera = resumed.pipeline.datamanager.train_dataset.cameras[0:1].to(model.device)
    model.eval()
    with torch.no_grad():
        outputs = model.get_outputs_for_camera(camera)
    for name in ("rgb", "clean", "depth"):
        assert outputs[name].shape[:2] == (24, 32) and torch.isfinite(outputs[name]).all(), name


def test_a_non_finite_state_is_never_written(scene, tmp_path):
    trainer = make_trainer(scene, tmp_path, 2)
    trainer.train()
    (good,) = checkpoints(trainer)
    good_bytes = good.read_bytes()
    with torch.no_grad():
        next(trainer.pipeline.model.medium_field.parameters()).view(-1)[0] = float("inf")
    with pytest.raises(NonFiniteTrainingError, match="medium_field"):
        trainer.save_checkpoint(5)
    assert checkpoints(trainer) == [good] and good.read_bytes() == good_bytes
    assert not list(trainer.staging_dir.glob("*"))


def test_a_save_killed_half_way_leaves_only_complete_checkpoints(scene, tmp_path):
    trainer = make_trainer(scene, tmp_path, 2)
    trainer.train()
    (good,) = checkpoints(trainer)
    real_save = torch.save

    def dies_half_way(obj, path, *args, **kwargs):
        real_save(obj, path, *args, **kwargs)
        data = Path(path).read_bytes()
        Path(path).write_bytes(data[: len(data) // 2])  # what a kill during the write leaves
        raise KeyboardInterrupt("killed while saving")

    with mock.patch("torch.save", dies_half_way), pytest.raises(KeyboardInterrupt):
        trainer.save_checkpoint(7)
    assert checkpoints(trainer) == [good]  # the half-written file never got a checkpoint's name
    resumed = make_trainer(scene, tmp_path / "resumed", 3, load_dir=good.parent)
    assert resumed._start_step == 2
    # the next save clears the leftover and lands atomically
    trainer.save_checkpoint(8)
    assert [p.name for p in checkpoints(trainer)] == ["step-000000008.ckpt"]
    assert not list(trainer.staging_dir.glob("*"))


def test_resume_from_an_empty_load_dir_says_why(scene, tmp_path, capsys):
    empty = tmp_path / "nerfstudio_models"
    empty.mkdir()
    with pytest.raises(SystemExit) as stopped:  # one line and exit status 1, as ns-train shows it
        make_trainer(scene, tmp_path, 2, load_dir=empty)
    assert stopped.value.code == 1
    assert f"{empty} holds no step-*.ckpt" in capsys.readouterr().out


def test_the_guard_can_be_switched_off(scene, tmp_path):
    trainer = make_trainer(scene, tmp_path, 3)
    assert trainer.guard is not None
    trainer.config.guard.enabled = False
    plain = trainer.config.setup(local_rank=0, world_size=1)
    assert plain.guard is None and not isinstance(plain.grad_scaler, GuardedGradScaler)


def inject_scale(trainer: SeathruTrainer, when: Callable[[int], bool], factor: float) -> None:
    """Every loss term times ``factor`` (finite) in the training steps where ``when(step)``."""
    model = trainer.pipeline.model
    original = model.get_loss_dict

    def scaled(*args, **kwargs):
        losses = original(*args, **kwargs)
        if model.training and when(trainer.step):
            return {name: value * factor for name, value in losses.items()}
        return losses

    model.get_loss_dict = scaled


def test_a_loss_spike_is_skipped_like_a_nan_step(scene, tmp_path, capsys):
    """One batch whose loss is far above the recent median is skipped: the parameters (and Adam's
    state) stay as they were; the non-finite count is not touched."""
    from seathru_nerfstudio.training import LOSS_SPIKE_WINDOW

    spike = LOSS_SPIKE_WINDOW + 1
    trainer = make_trainer(scene, tmp_path, spike + 2)
    inject_scale(trainer, lambda step: step == spike, 1e3)
    params = snapshot_each_step(trainer)
    trainer.train()

    assert trainer.guard.spike_skipped_steps == [spike]
    assert trainer.guard.skipped_steps == [] and trainer.guard.consecutive_bad_steps == 0
    for name, value in params[spike].items():
        assert torch.equal(value, params[spike + 1][name]), f"{name} changed in the skipped step"
    out = capsys.readouterr().out
    assert f"step {spike}: optimiser step skipped" in out and "loss spike" in out


def _guard_steps(guard, losses):
    """Feed ``losses`` to ``guard`` as successive steps (one parameter with a finite gradient);
    the steps it skipped."""
    parameter = torch.nn.Parameter(torch.zeros(2))
    parameter.grad = torch.ones(2)
    skipped = []
    for step, loss in enumerate(losses):
        guard.start_step()
        guard.record_loss(torch.tensor(loss))
        if guard.decide({"fields": [parameter]}, ["fields"]):
            skipped.append(step)
        guard.finish_step(step, {"rgb_loss": torch.tensor(loss)}, None)
    return skipped


def test_a_lasting_change_of_the_loss_level_is_followed_within_half_a_window():
    """The median window holds skipped steps too: a loss that jumps 100× and stays there is
    skipped for at most half a window, then trained on; a jump under the ratio is never skipped;
    ratio 0 switches the check off."""
    from seathru_nerfstudio.training import LOSS_SPIKE_WINDOW, NonFiniteGuard, NonFiniteGuardConfig

    generator = torch.Generator().manual_seed(0)
    calm = (0.02 * (1 + 0.3 * torch.rand(LOSS_SPIKE_WINDOW, generator=generator))).tolist()
    guard = NonFiniteGuard(NonFiniteGuardConfig(loss_spike_ratio=10.0))
    skipped = _guard_steps(guard, calm + [2.0] * (2 * LOSS_SPIKE_WINDOW))
    first = LOSS_SPIKE_WINDOW
    assert skipped == list(range(first, first + len(skipped))) and 1 <= len(skipped) <= LOSS_SPIKE_WINDOW // 2 + 1
    assert guard.skipped_steps == [] and guard.consecutive_bad_steps == 0
    assert _guard_steps(NonFiniteGuard(NonFiniteGuardConfig(loss_spike_ratio=10.0)), calm + [0.15] * 5) == []
    assert _guard_steps(NonFiniteGuard(NonFiniteGuardConfig(loss_spike_ratio=0.0)), calm + [2.0] * 5) == []
    # a level at or below zero (a loss with negative terms) has no ratio: nothing is a spike there
    negative = [-value for value in calm]
    assert _guard_steps(NonFiniteGuard(NonFiniteGuardConfig(loss_spike_ratio=10.0)), negative + [0.5] * 5) == []
    with pytest.raises(ValueError, match="loss_spike_ratio"):
        NonFiniteGuard(NonFiniteGuardConfig(loss_spike_ratio=0.5))
