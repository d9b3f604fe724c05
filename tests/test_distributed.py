"""Two processes on the CPU: a Gloo run of a tiny ``seathru-nerf-lite`` through nerfstudio's
``Trainer`` with ``world_size``/``local_rank`` (issue 11).

Each rank writes what it saw to a file; the assertions run here, in the parent."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Dict

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch.nn.parallel import DistributedDataParallel as DDP

from seathru_nerfstudio.compat import load_checkpoint
from tiny_training import make_scene, tiny_config

pytestmark = pytest.mark.slow  # trains through nerfstudio's Trainer

WORLD = 2
ITERATIONS = 4


def _grads(trainer, ray_bundle, batch, sync: bool) -> Dict[str, torch.Tensor]:
    """Gradients of one loss on ``ray_bundle``: this rank's own (``sync=False``, DDP's
    ``no_sync``) or DDP's all-reduced ones. Same sampling noise both times."""
    ddp = trainer.pipeline._model
    model = trainer.pipeline.model
    trainer.optimizers.zero_grad_all()
    torch.manual_seed(1234)
    with contextlib.nullcontext() if sync else ddp.no_sync():
        outputs = ddp(ray_bundle)
        loss_dict = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
        sum(loss_dict.values()).backward()
    grads = {n: p.grad.detach().clone() for n, p in model.named_parameters() if p.grad is not None}
    trainer.optimizers.zero_grad_all()
    return grads


def _rank(local_rank: int, dist_url: str, scene: str, out: str) -> None:
    from seathru_nerfstudio.distributed import use_gloo_pipeline
    from seathru_nerfstudio.training import SeathruTrainer

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=dist_url, world_size=WORLD, rank=local_rank)
    try:
        config = use_gloo_pipeline(tiny_config(Path(scene), Path(out), ITERATIONS, steps_per_save=2))
        torch.manual_seed(42 + local_rank)  # what nerfstudio's train_loop does: seed + global rank
        trainer = config.setup(local_rank=local_rank, world_size=WORLD)
        assert isinstance(trainer, SeathruTrainer)
        trainer.setup()
        assert isinstance(trainer.pipeline._model, DDP)
        model = trainer.pipeline.model
        initial = {k: v.detach().clone() for k, v in model.named_parameters()}

        ray_bundle, batch = trainer.pipeline.datamanager.next_train(0)
        local = _grads(trainer, ray_bundle, batch, sync=False)
        synced = _grads(trainer, ray_bundle, batch, sync=True)

        # one step through nerfstudio's training step (guard included), then a whole short run
        trainer.pipeline.train()
        trainer.train_iteration(0)
        after_step = {k: v.detach().clone() for k, v in model.named_parameters()}
        trainer.train()
        final = {k: v.detach().clone() for k, v in model.named_parameters()}

        # what rank 1 writes when asked to save: nothing
        saved_elsewhere = Path(out) / f"rank{local_rank}_save_probe"
        trainer.checkpoint_dir = saved_elsewhere
        trainer.save_checkpoint(99)
        torch.save(
            {
                "initial": initial,
                "local": local,
                "synced": synced,
                "after_step": after_step,
                "final": final,
                "pixels": batch["indices"].clone(),
                "probe_written": saved_elsewhere.exists() and any(saved_elsewhere.iterdir()),
                "step": trainer.step,
            },
            Path(out) / f"rank{local_rank}.pt",
        )
    finally:
        dist.destroy_process_group()


def two_ranks(root: Path) -> dict:
    """:func:`_rank` in two spawned processes; what each wrote. Listed in ``BACKGROUND_JOBS``: the
    suite starts it at collection (conftest's ``background_job``)."""
    from seathru_nerfstudio.distributed import free_local_url

    scene = make_scene(root)
    out = root / "out"
    out.mkdir()
    mp.spawn(_rank, args=(free_local_url(), str(scene), str(out)), nprocs=WORLD, join=True)
    return {"out": out, "results": [torch.load(out / f"rank{r}.pt", weights_only=False) for r in range(WORLD)]}


@pytest.fixture(scope="module")
def ranks(background_job) -> dict:
    return background_job(two_ranks)


def test_both_ranks_take_part_and_gradients_are_averaged(ranks):
    r0, r1 = ranks["results"]
    assert not torch.equal(r0["pixels"], r1["pixels"]), "both ranks trained on the same rays"
    assert r0["local"].keys() == r1["local"].keys() == r0["synced"].keys()
    differs = [k for k in r0["local"] if not torch.allclose(r0["local"][k], r1["local"][k])]
    assert differs, "the ranks' own gradients are identical: they did not see different data"
    for name in r0["synced"]:
        mean = (r0["local"][name] + r1["local"][name]) / 2
        assert torch.allclose(r0["synced"][name], mean, atol=1e-6, rtol=1e-4), name
        assert torch.equal(r0["synced"][name], r1["synced"][name]), name


def test_parameters_are_identical_across_ranks_after_a_step_medium_field_included(ranks):
    r0, r1 = ranks["results"]
    assert any("medium_field" in k for k in r0["after_step"]), "the medium field has no parameters?"
    for key in ("initial", "after_step", "final"):
        for name, value in r0[key].items():
            assert torch.equal(value, r1[key][name]), f"{key}: {name} differs between ranks"
    moved = [k for k in r0["initial"] if not torch.equal(r0["initial"][k], r0["after_step"][k])]
    assert any("medium_field" in k for k in moved) and any(k.startswith("field.") for k in moved), moved
    assert r0["step"] == r1["step"] == ITERATIONS - 1


def test_only_rank_0_writes_checkpoints_and_logs(ranks):
    r0, r1 = ranks["results"]
    assert r0["probe_written"] and not r1["probe_written"]
    run = ranks["out"] / "tiny" / "seathru-nerf-lite" / "run"
    assert [p.name for p in (run / "nerfstudio_models").iterdir()] == [f"step-{ITERATIONS - 1:09d}.ckpt"]
    assert len(list(run.glob("events.out.tfevents.*"))) == 1
    state = load_checkpoint(run / "nerfstudio_models" / f"step-{ITERATIONS - 1:09d}.ckpt")
    saved = {k[len("_model.module.") :]: v for k, v in state["pipeline"].items() if k.startswith("_model.module.")}
    for name, value in r0["final"].items():
        assert torch.equal(saved[name], value), name


def cpu_entry_point_run(root: Path):
    """``python -m seathru_nerfstudio.distributed`` with ``ns-train``'s arguments and two CPU processes
    (``{"root", "result"}``: the folder, its ``subprocess.CompletedProcess``). Listed in
    ``BACKGROUND_JOBS``: the suite starts it at collection (conftest's ``background_job``)."""
    import os
    import subprocess
    import sys

    from tiny_training import TINY_MODEL_ARGS

    scene = make_scene(root)
    args = [
        sys.executable, "-m", "seathru_nerfstudio.distributed", "seathru-nerf-lite",
        "--data", str(scene), "--output-dir", str(root / "out"), "--timestamp", "cli",
        "--machine.device-type", "cpu", "--machine.num-devices", "2",
        "--max-num-iterations", "3", "--steps-per-save", "2", *TINY_MODEL_ARGS,
    ]  # fmt: skip
    env = dict(os.environ, PYTHONWARNINGS="ignore", OMP_NUM_THREADS="1")
    return {"root": root, "result": subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)}


BACKGROUND_JOBS = [two_ranks, cpu_entry_point_run]


def test_the_cpu_entry_point_trains_with_two_processes(background_job):
    """``python -m seathru_nerfstudio.distributed`` with ``ns-train``'s arguments: two Gloo
    processes, one run folder, one checkpoint at the last step."""
    job = background_job(cpu_entry_point_run)
    result, root = job["result"], job["root"]
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "2 processes here, 2 in all" in result.stdout
    (run,) = list((root / "out").glob("*/seathru-nerf-lite/cli"))
    assert [p.name for p in (run / "nerfstudio_models").iterdir()] == ["step-000000002.ckpt"]
    state = load_checkpoint(run / "nerfstudio_models" / "step-000000002.ckpt")
    assert any(k.startswith("_model.module.medium_field") for k in state["pipeline"])  # saved from the DDP wrapper


def _read_open_water(local_rank: int, dist_url: str, out: str) -> None:
    from seathru_nerfstudio.medium_start import OpenWaterColour

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=dist_url, world_size=WORLD, rank=local_rank)
    try:
        read = OpenWaterColour()
        colour = torch.tensor([0.1, 0.2, 0.3]) * (local_rank + 1)  # each rank sees its own water
        rays = (10, 30)[local_rank]
        level = torch.stack([torch.linspace(-0.5, 0.4, rays), torch.full((rays,), 0.9)], dim=1) * (local_rank + 1) / 2
        read.add(colour.expand(rays, 3), torch.ones(rays, 1), torch.full((rays, 1), (-0.1, 0.2)[local_rank]), level)
        alone = read.mean()
        pooled = read.pooled("cpu")
        restored = OpenWaterColour()
        restored.set_extra_state(read.get_extra_state())  # each rank loads the checkpoint rank 0 wrote
        result = {"alone": alone, "pooled": pooled.mean(), "rise": pooled.rise(), "counts": (pooled.open_rays, pooled.rays)}
        result["restored"] = (restored.open_rays, restored.rays)
        result["above_level_rays"] = float(pooled.above_gram[0, 0])
        result["level_extent"] = pooled.level_extent
        torch.save(result, Path(out) / f"read{local_rank}.pt")
    finally:
        dist.destroy_process_group()


def test_every_rank_reads_the_same_open_water_from_all_ranks_rays(tmp_path):
    """The veil is read from the open rays of every process (10 rays of one colour on rank 0, 30 of
    twice it, higher up, on rank 1: the ray-weighted mean 1.75 times rank 0's, and one rise), so that
    the ranks hold one veil; each rank alone would hold its own. Only rank 0 writes checkpoints, so
    only it takes back the sums from one: the pooled mean of a resumed run counts them once."""
    from seathru_nerfstudio.distributed import free_local_url

    mp.spawn(_read_open_water, args=(free_local_url(), str(tmp_path)), nprocs=WORLD, join=True)
    r0, r1 = (torch.load(tmp_path / f"read{r}.pt", weights_only=False) for r in range(WORLD))
    water = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    assert not torch.allclose(r0["alone"], r1["alone"])
    torch.testing.assert_close(r0["pooled"], water * (10 * 1 + 30 * 2) / 40, rtol=1e-6, atol=1e-7)
    assert torch.equal(r0["pooled"], r1["pooled"]) and r0["counts"] == r1["counts"] == (40, 40)
    (up0, slope0, highest0), (up1, slope1, highest1) = r0["rise"], r1["rise"]
    assert torch.equal(up0, up1) and highest0 == highest1 and torch.equal(slope0, slope1)
    assert up0.tolist() == pytest.approx([(10 * -0.1 + 30 * 0.2) / 40] * 3) and highest0 == pytest.approx(0.2)
    assert torch.all(slope0 > 0)  # the brighter water is the higher
    assert r0["restored"] == (10, 10) and r1["restored"] == (0, 0)
    assert r0["above_level_rays"] == r1["above_level_rays"] == 30  # rank 1's rays, above the level, counted on both
    # the extent round the horizon is the largest over the ranks (rank 0's rays, below the level, count for none)
    expected_extent = torch.tensor([0.4, 0.9, 0.5, -0.9], dtype=torch.float64)
    torch.testing.assert_close(r0["level_extent"], expected_extent)
    assert torch.equal(r0["level_extent"], r1["level_extent"])


def _guard_on_rank(local_rank: int, dist_url: str, out: str) -> None:
    from datetime import timedelta

    from seathru_nerfstudio.training import LOSS_SPIKE_WINDOW, NonFiniteGuard, NonFiniteGuardConfig

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=dist_url, world_size=WORLD, rank=local_rank, timeout=timedelta(seconds=60))
    try:
        guard = NonFiniteGuard(NonFiniteGuardConfig(loss_spike_ratio=10.0), world_size=WORLD)
        parameter = torch.nn.Parameter(torch.zeros(3))
        # rank 0 has a full window at a positive level (checked); rank 1 a negative level (unchecked)
        level = 0.02 if local_rank == 0 else -0.02
        losses = [level] * LOSS_SPIKE_WINDOW + [(2.0, 0.0)[local_rank]]
        skipped = []
        for step, loss in enumerate(losses):
            guard.start_step()
            parameter.grad = torch.ones(3)
            guard.record_loss(torch.tensor(loss))
            if guard.decide({"fields": [parameter]}, ["fields"]):
                skipped.append(step)
            guard.finish_step(step, {"rgb_loss": torch.tensor(loss)}, None)
        torch.save({"skipped": skipped, "spikes": guard.spike_skipped_steps}, Path(out) / f"guard{local_rank}.pt")
    finally:
        dist.destroy_process_group()


def test_a_loss_spike_on_one_rank_skips_the_step_on_every_rank(tmp_path):
    """Rank 0 checks for a spike (a positive median) and sees one; rank 1 does not check (its
    median is negative). Both all-reduce a flag vector of one size, and both skip that step."""
    from seathru_nerfstudio.distributed import free_local_url
    from seathru_nerfstudio.training import LOSS_SPIKE_WINDOW

    mp.spawn(_guard_on_rank, args=(free_local_url(), str(tmp_path)), nprocs=WORLD, join=True)
    r0, r1 = (torch.load(tmp_path / f"guard{r}.pt") for r in range(WORLD))
    assert r0["skipped"] == r1["skipped"] == [LOSS_SPIKE_WINDOW]
    assert r0["spikes"] == r1["spikes"] == [LOSS_SPIKE_WINDOW]
