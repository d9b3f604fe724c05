"""``ns-train`` with a given ``--machine.seed`` on one torch thread trains the same model twice,
and another seed a different one: the rays drawn in nerfstudio's data worker follow the seed
(``data/seeded_sampler.py``; nerfstudio leaves that worker unseeded)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
import torch

from seathru_nerfstudio.compat import load_checkpoint

from tiny_checkpoint import start_group, stop_group
from tiny_training import BIN, TINY_MODEL_ARGS, make_scene

pytestmark = pytest.mark.slow  # trains through nerfstudio's Trainer

STEPS = 12


def start_training(scene: Path, out: Path, name: str, seed: int) -> subprocess.Popen:
    command = [
        str(BIN / "ns-train"), "seathru-nerf-lite",
        "--data", str(scene),
        "--output-dir", str(out),
        "--experiment-name", "repeat",
        "--timestamp", name,
        "--max-num-iterations", str(STEPS),
        "--machine.seed", str(seed),
        *TINY_MODEL_ARGS,
    ]  # fmt: skip
    env = dict(os.environ, PYTHONWARNINGS="ignore", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    with open(out.parent / f"{name}.log", "w") as log:
        return start_group(command, env=env, stdout=log, stderr=subprocess.STDOUT)


def trained_state(out: Path, name: str) -> dict:
    (checkpoint,) = (out / "repeat" / "seathru-nerf-lite" / name / "nerfstudio_models").glob("step-*.ckpt")
    return load_checkpoint(checkpoint)["pipeline"]


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    """Three ``ns-train`` processes, run side by side (each on one thread: the start-up, importing
    nerfstudio, is most of a 12-step run)."""
    root = tmp_path_factory.mktemp("repeatable")
    scene = make_scene(root)
    runs = {name: start_training(scene, root / "outputs", name, seed) for name, seed in (("a", 3), ("b", 3), ("c", 4))}
    try:
        for name, proc in runs.items():
            proc.wait(timeout=900)
            assert proc.returncode == 0, (root / f"{name}.log").read_text()[-5000:]
    finally:
        for proc in runs.values():
            stop_group(proc)  # a run left behind by a failure, and any data worker
    return {name: trained_state(root / "outputs", name) for name in runs}


def test_the_same_seed_trains_the_same_model(states):
    first, again = states["a"], states["b"]
    assert first.keys() == again.keys()
    for key, value in first.items():
        assert torch.equal(value, again[key]), key


def test_another_seed_trains_another_model(states):
    first, other = states["a"], states["c"]
    hash_tables = [key for key in first if "field" in key and first[key].is_floating_point() and first[key].numel() > 1000]
    assert hash_tables, sorted(first)
    assert any(not torch.equal(first[key], other[key]) for key in hash_tables)
