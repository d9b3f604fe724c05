"""Per-iteration cost of the non-finite guard, measured side by side.

Two ``seathru-nerf-lite`` trainers on the same scene, one with the guard and one without
(``--guard.enabled False``), take turns iteration by iteration in this one process, so both see
the same machine load; the figure is the ratio of their median iteration times. Also timed
alone: the guard's own check (finiteness of the loss and of every gradient, one host sync).

    python scripts/guard_overhead.py [--iterations 60] [--scene DIR]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def build(scene: Path, out: Path, guard: bool):
    from seathru_nerfstudio.config import seathru_nerf_lite_config

    config = seathru_nerf_lite_config()
    config.data = config.pipeline.datamanager.data = scene
    config.output_dir, config.experiment_name, config.timestamp = out, "overhead", "on" if guard else "off"
    config.vis = "tensorboard"
    config.guard.enabled = guard
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def timed_iteration(trainer, step: int) -> float:
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    t0 = time.perf_counter()
    trainer.pipeline.train()
    for callback in trainer.callbacks:
        callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    trainer.train_iteration(step)
    for callback in trainer.callbacks:
        callback.run_callback_at_location(step, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=60)
    parser.add_argument("--scene", type=Path, default=None, help="default: a 64x48, 10-view seathru-synth scene")
    args = parser.parse_args()

    import torch

    from seathru_nerfstudio.quiet import silence_upstream_warnings

    silence_upstream_warnings()

    work = Path(tempfile.mkdtemp(prefix="guard-overhead-"))
    scene = args.scene
    if scene is None:
        scene = work / "scene"
        synth = Path(sys.executable).parent / "seathru-synth"
        subprocess.run([str(synth), "--output-dir", str(scene), "--width", "64", "--height", "48", "--num-views", "10"],
                       check=True, capture_output=True)  # fmt: skip
    torch.manual_seed(0)
    guarded = build(scene, work / "out", True)
    torch.manual_seed(0)
    plain = build(scene, work / "out", False)
    times = {"on": [], "off": []}
    for step in range(args.iterations):
        order = [("on", guarded), ("off", plain)] if step % 2 else [("off", plain), ("on", guarded)]
        for name, trainer in order:
            trainer.step = step
            times[name].append(timed_iteration(trainer, step))

    # the guard's check alone, on the guarded trainer's last real gradients
    trainer = guarded
    trainer.optimizers.zero_grad_all()
    _, loss_dict, _ = trainer.pipeline.get_train_loss_dict(step=args.iterations)
    loss = sum(loss_dict.values())
    loss.backward()
    groups = list(trainer.optimizers.parameters.keys())
    checks = []
    for _ in range(50):
        t0 = time.perf_counter()
        trainer.guard.start_step()
        trainer.guard.record_loss(loss)
        trainer.guard.decide(trainer.optimizers.parameters, groups)
        checks.append(time.perf_counter() - t0)

    skip = min(10, args.iterations // 5)  # warm-up
    on, off = statistics.median(times["on"][skip:]), statistics.median(times["off"][skip:])
    check = statistics.median(checks)
    n_params = sum(p.numel() for p in trainer.pipeline.model.parameters())
    print(f"seathru-nerf-lite, {args.iterations} iterations each, interleaved, torch threads {torch.get_num_threads()}")
    print(f"median s/iteration: guard on {on:.4f}, guard off {off:.4f}, ratio {on / off:.4f} ({100 * (on / off - 1):+.2f}%)")
    print(f"guard check alone ({n_params} parameters): {1e3 * check:.3f} ms = {100 * check / off:.2f}% of an iteration")


if __name__ == "__main__":
    main()
