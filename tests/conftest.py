"""Fixtures shared by the end-to-end tests: one tiny SeaThru run per test session.

``tiny_run`` trains it once through the real CLIs (``seathru-synth``, ``ns-train``); the viewer,
video and CLI tests all read it and write only into their own folders. ``ns_eval_results`` is
the real ``ns-eval`` on it, also once, and ``tiny_pipeline`` its pipeline loaded in this
process; ``ns_render`` runs nerfstudio's ``ns-render`` entry point
in-process (the CLI's start-up, importing nerfstudio, is paid once). Every test that uses
``tiny_run`` is marked ``slow`` (``pytest -m "not slow"`` leaves them out).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Dict

import pytest

sys.path.insert(0, str(Path(__file__).parent / "browser"))
import tiny_checkpoint  # noqa: E402


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Dict[str, Path]:
    """``{"root", "scene", "config"}`` of a checkpoint trained once for the session."""
    return tiny_checkpoint.train_tiny(tmp_path_factory.mktemp("tiny_run"))


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
        if "tiny_run" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.slow)
