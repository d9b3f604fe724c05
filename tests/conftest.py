"""Fixtures shared by the tests; each expensive one is built once per ``pytest`` run.

* ``tiny_trained_run``: one tiny ``seathru-nerf-lite`` run through the real CLIs
  (``seathru-synth``, then ``ns-train``; see ``tests/browser/tiny_checkpoint.py`` for its scene,
  model size and iterations), trained once per run: ``{"root", "scene", "config"}``, the run
  folder being ``config.parent`` (``config.yml``, ``nerfstudio_models/step-*.ckpt``, TensorBoard
  events with the loss of every step). Use it for anything that needs *a* trained model or a
  checkpoint; write only into your own ``tmp_path``, never into the run. ``tiny_run`` is the
  same run under its older name.
* ``ns_eval_results``: the real ``ns-eval`` on it, also once; ``tiny_pipeline`` its pipeline
  loaded in this process (``eval_setup``, as ns-eval and ns-render load it);
* ``ns_render``: nerfstudio's ``ns-render`` entry point in-process (the CLI's start-up,
  importing nerfstudio, is paid once).

Every process of the suite computes on one thread (``OMP_NUM_THREADS=1`` unless set, and
``torch.set_num_threads(1)`` here): on a 2-core machine torch's two threads wait on each other
whenever the other core is busy (a CLI the tests started, another program), and small tensors
pay for it most: a 4000-pixel loss took 7.8 ms on two threads against 0.09 ms on one (load 4.5),
and ``test_medium_fit.py`` 145 s against 10 s.

Every test that uses the trained run is marked ``slow`` (``pytest -m "not slow"`` leaves them
out). The suite runs in a random order (``pytest-randomly``, in the ``test`` extra): every test
file must pass alone and in any order; the seed is printed at the end of the run
(``--randomly-seed=N`` repeats an order, ``-p no:randomly`` turns the shuffle off). pytest-randomly also reseeds ``random`` and NumPy's global generator before
each test; tests that need a seed set their own.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Dict

import pytest

sys.path.insert(0, str(Path(__file__).parent / "browser"))
import tiny_checkpoint  # noqa: E402

os.environ.setdefault("OMP_NUM_THREADS", "1")  # the CLIs the tests start, too
os.environ.setdefault("MKL_NUM_THREADS", os.environ["OMP_NUM_THREADS"])


def pytest_configure(config) -> None:
    import torch

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


@pytest.fixture(scope="session")
def tiny_trained_run(tmp_path_factory) -> Dict[str, Path]:
    """``{"root", "scene", "config"}`` of a tiny ``seathru-nerf-lite`` run trained once per
    ``pytest`` run through ``seathru-synth`` and ``ns-train`` (:func:`tiny_checkpoint.train_tiny`)."""
    return tiny_checkpoint.train_tiny(tmp_path_factory.mktemp("tiny_trained_run"))


@pytest.fixture(scope="session")
def tiny_run(tiny_trained_run) -> Dict[str, Path]:
    """``tiny_trained_run`` under its older name."""
    return tiny_trained_run


@pytest.fixture(scope="session")
def ns_eval_results(tiny_run, tmp_path_factory) -> Dict[str, float]:
    """``results`` of nerfstudio's ``ns-eval`` CLI on the tiny run."""
    output = tmp_path_factory.mktemp("ns_eval") / "eval.json"
    tiny_checkpoint.run(
        tiny_checkpoint.BIN / "ns-eval", "--load-config", tiny_run["config"], "--output-path", output, cwd=output.parent
    )
    return json.loads(output.read_text())["results"]


@pytest.fixture(scope="session")
def tiny_pipeline(tiny_run):
    """The tiny run's pipeline, loaded as ns-eval and ns-render load it (``eval_setup``), once."""
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(tiny_run["config"], test_mode="test")
    return pipeline


@pytest.fixture
def ns_render():
    """``ns_render(*args)``: ``ns-render <args>`` through nerfstudio's own entry point, in this
    process, with one math thread (the machine's two cores are shared)."""
    import torch
    from nerfstudio.scripts import render

    def run(*args) -> None:
        argv, threads = sys.argv, torch.get_num_threads()
        sys.argv = ["ns-render", *[str(a) for a in args]]
        torch.set_num_threads(1)
        try:
            render.entrypoint()
        finally:
            sys.argv = argv
            torch.set_num_threads(threads)

    return run


def pytest_collection_modifyitems(items) -> None:
    for item in items:
        if {"tiny_run", "tiny_trained_run"} & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)


def pytest_terminal_summary(terminalreporter, config) -> None:
    """The order's seed, also under ``-q`` (which hides pytest-randomly's header line)."""
    seed = getattr(config.option, "randomly_seed", None)
    if seed is not None and config.getoption("randomly_reorganize", True):
        terminalreporter.write_line(f"test order: pytest-randomly seed {seed} (repeat it with --randomly-seed={seed})")
