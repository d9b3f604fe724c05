"""``ns-train`` with a given ``--machine.seed`` on one torch thread trains the same model twice,
and another seed a different one: the rays drawn in nerfstudio's data worker follow the seed
(``data/seeded_sampler.py``; nerfstudio leaves that worker unseeded)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from seathru_nerfstudio.compat import load_checkpoint

import forked_cli
from tiny_training import TINY_MODEL_ARGS, make_scene

pytestmark = pytest.mark.slow  # trains through nerfstudio's Trainer

STEPS = 12


def train(scene: Path, out: Path, name: str, seed: int) -> None:
    """``ns-train`` in a process of its own (``forked_cli``: nerfstudio is imported once, not per run,
    which was most of a 12-step run), on one thread (the suite's ``OMP_NUM_THREADS``)."""
    result = forked_cli.run(
        "ns-train", "seathru-nerf-lite",
        "--data", scene,
        "--output-dir", out,
        "--experiment-name", "repeat",
        "--timestamp", name,
        "--max-num-iterations", STEPS,
        "--machine.seed", seed,
        *TINY_MODEL_ARGS,
        cwd=out.parent, timeout_s=600,
    )  # fmt: skip
    assert result.returncode == 0 and not result.stray, (result.stray, result.output[-5000:])


def trained_state(out: Path, name: str) -> dict:
    (checkpoint,) = (out / "repeat" / "seathru-nerf-lite" / name / "nerfstudio_models").glob("step-*.ckpt")
    return load_checkpoint(checkpoint)["pipeline"]


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    """Three ``ns-train`` runs, one after the other: seeds 3, 3 and 4."""
    root = tmp_path_factory.mktemp("repeatable")
    scene = make_scene(root)
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        train(scene, root / "outputs", name, seed)
    return {name: trained_state(root / "outputs", name) for name in ("a", "b", "c")}


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
