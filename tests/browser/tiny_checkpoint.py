"""A tiny SeaThru checkpoint through the real CLIs (seathru-synth, ns-train), for the viewer,
video and CLI tests (``tests/conftest.py`` trains it once per session): enough iterations of a
small model for its loss to fall clearly, cheap to render on a loaded CPU."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Dict

import forked_cli  # tests/ is on sys.path under pytest
from tiny_training import BIN, SMALL_MODEL_ARGS  # noqa: F401 - BIN for the tests that start CLIs themselves

ITERATIONS = 40
"""Enough for the training loss to fall to well under half (the veiling light fits first). All
of it is ``seathru-nerf-lite``'s first stage (``medium_first_steps``, 200): the veiling light and
the SfM geometry learn, the object colour does not."""
WIDTH, HEIGHT, VIEWS = 64, 48, 8


def quiet_env(threads: int = 1) -> Dict[str, str]:
    """One math thread per process: the machine's two cores are shared."""
    return dict(os.environ, PYTHONWARNINGS="ignore", OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))


def start_group(args, **kwargs) -> subprocess.Popen:
    """Start a long-running CLI in its own process group: nerfstudio's data manager spawns
    worker processes that outlive a plain terminate() of the CLI."""
    return subprocess.Popen([str(a) for a in args], start_new_session=True, **kwargs)


def stop_group(proc: subprocess.Popen, timeout: float = 30) -> None:
    """Stop the CLI and every process it started (its process group): SIGTERM, then SIGKILL
    whatever is left after ``timeout`` seconds."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break  # nobody left
        deadline = time.time() + timeout
        while time.time() < deadline:
            proc.poll()  # reap the leader, or the group never looks empty
            try:
                os.killpg(proc.pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.2)
        else:
            continue
        break
    proc.wait(timeout)


def run(command: str, *args, cwd: Path, timeout: float = 900) -> forked_cli.Result:
    """The installed command ``command *args`` in ``cwd``, through :mod:`forked_cli`: the same entry
    point as typed in a shell, in a child of a fork server that has nerfstudio imported, so it pays
    no start-up imports, and the data worker ``ns-train`` spawns does not import the console script
    again as ``__mp_main__`` (about 15 CPU-seconds each on the test machine). Asserts it succeeded."""
    result = forked_cli.run(command, *[str(a) for a in args], cwd=cwd, timeout_s=timeout)
    assert result.returncode == 0, f"{command} failed ({result.returncode}):\n{result.output[-8000:]}"
    return result


def train_tiny(root: Path, iterations: int = ITERATIONS, width: int = WIDTH, height: int = HEIGHT) -> Dict[str, Path]:
    """Synthetic water scene (``VIEWS`` views) and a checkpoint after ``iterations`` steps, with
    the training loss logged at every step (TensorBoard events in the run folder).

    ``SEATHRU_TINY_CHECKPOINT=<dir>`` reuses (or first fills) that folder instead: for
    iterating on the tests locally."""
    reuse = os.environ.get("SEATHRU_TINY_CHECKPOINT")
    if reuse:
        root = Path(reuse)
        root.mkdir(parents=True, exist_ok=True)
        found = list((root / "outputs").glob("*/seathru-nerf-lite/*/config.yml"))
        if found:
            return {"root": root, "scene": root / "scene", "config": found[0]}
    scene = root / "scene"
    run("seathru-synth", "--output-dir", scene, "--width", width, "--height", height, "--num-views", VIEWS, cwd=root)
    run(
        "ns-train", "seathru-nerf-lite",
        "--data", scene,
        "--output-dir", root / "outputs",
        "--max-num-iterations", iterations,
        "--steps-per-save", iterations,
        "--steps-per-eval-batch", 1000,
        "--steps-per-eval-image", 1000,
        "--steps-per-eval-all-images", 1000,
        "--logging.steps-per-log", 1,
        "--pipeline.datamanager.train-num-rays-per-batch", 256,
        *SMALL_MODEL_ARGS,
        "--vis", "tensorboard",
        cwd=root,
    )  # fmt: skip
    (config,) = list((root / "outputs").glob("*/seathru-nerf-lite/*/config.yml"))
    return {"root": root, "scene": scene, "config": config}
