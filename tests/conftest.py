"""Fixtures shared by the tests; each expensive one is built once per ``pytest`` run.

* ``tiny_trained_run``: one tiny ``seathru-nerf-lite`` run through the real CLIs
  (``seathru-synth``, then ``ns-train``; see ``tests/browser/tiny_checkpoint.py`` for its scene,
  model size and iterations), trained once per run: ``{"root", "scene", "config"}``, the run
  folder being ``config.parent`` (``config.yml``, ``nerfstudio_models/step-*.ckpt``, TensorBoard
  events with the loss of every step): 64x48, 8 views, 40 steps, all of them the first stage
  (veiling light and SfM geometry; the object colour is untrained). Use it for anything that
  needs *a* trained model or a checkpoint; write only into your own ``tmp_path``, never into
  the run. ``tiny_run`` is the same run under its older name. Its training (and ``ns-eval``
  after it) starts in the background as soon as the tests are collected, if any of them needs it.
* ``ns_eval_results``: the real ``ns-eval`` on it, also once; ``tiny_pipeline`` its pipeline
  loaded in this process (``eval_setup``, as ns-eval and ns-render load it);
* ``ns_render``: nerfstudio's ``ns-render`` entry point in-process (the CLI's start-up,
  importing nerfstudio, is paid once);
* ``decomposition_run``: the ``results.json`` of the decomposition check's short ``seathru-bench
  run`` (``tiny_training.DECOMPOSITION_BENCH``), started in the background at collection like the
  tiny run: the longest work of the suite overlaps the rest.
* ``background_job``: ``background_job(job)`` is the result of ``job``, a function of a fresh
  folder that a test module lists in its ``BACKGROUND_JOBS`` (work that only starts CLIs and
  waits for them: a training run to kill, a two-process run). The listed jobs start at collection,
  one after the other on a thread of their own, so that they run on the core the tests leave free.
  A module's ``TINY_RUN_JOBS`` are the same for work on the tiny run: functions of the run
  (``tiny_trained_run``'s dict) and a fresh folder, queued on the tiny run's thread after
  ``ns-eval`` (a viewer to start and drive, a video to render with the ``ns-render`` CLI).

Every process of the suite computes on one thread (``OMP_NUM_THREADS=1`` unless set, and
``torch.set_num_threads(1)`` here): on a 2-core machine torch's two threads wait on each other
whenever the other core is busy (a CLI the tests started, another program), and small tensors
pay for it most: a 4000-pixel loss took 7.8 ms on two threads against 0.09 ms on one (load 4.5),
and ``test_medium_fit.py`` 145 s against 10 s. NumPy's OpenBLAS is limited to one thread too
(``threadpoolctl``): a pytest plugin imports NumPy before this file sets ``OMP_NUM_THREADS``, and
its second thread spins while it waits, so a least-squares test that takes 0.2 s alone took 34-38 s
beside the suite's background work.

Every test that uses the trained run is marked ``slow`` (``pytest -m "not slow"`` leaves them
out). The suite runs in a random order (``pytest-randomly``, in the ``test`` extra): every test
file must pass alone and in any order; the seed is printed at the end of the run
(``--randomly-seed=N`` repeats an order, ``-p no:randomly`` turns the shuffle off).
pytest-randomly also reseeds ``random`` and NumPy's global generator before each test; tests
that need a seed set their own.
"""

from __future__ import annotations

import json
import os
import sys
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Dict, Sequence

import pytest

sys.path.insert(0, str(Path(__file__).parent / "browser"))
import tiny_checkpoint  # noqa: E402
import tiny_training  # noqa: E402

os.environ.setdefault("OMP_NUM_THREADS", "1")  # the CLIs the tests start, too
os.environ.setdefault("MKL_NUM_THREADS", os.environ["OMP_NUM_THREADS"])


def pytest_configure(config) -> None:
    import threadpoolctl
    import torch

    threads = int(os.environ["OMP_NUM_THREADS"])
    torch.set_num_threads(threads)
    threadpoolctl.threadpool_limits(limits=threads)  # NumPy's OpenBLAS, loaded before OMP_NUM_THREADS was set


TRAINED_RUN_USERS = {"tiny_trained_run", "tiny_run", "ns_eval_results", "tiny_pipeline"}
_background: Dict[str, Future] = {}


def _start_in_background(root: Path, tmp_path_factory, run_jobs: Sequence[Callable[[dict, Path], Any]] = ()) -> None:
    """Train the tiny run, then run ``ns-eval`` on it, then ``run_jobs`` (test modules'
    ``TINY_RUN_JOBS``), one after the other on a thread of this process that only waits for the
    CLIs (``_background["run"]``, ``_background["eval"]``, ``_jobs[job]``)."""
    worker = ThreadPoolExecutor(1, thread_name_prefix="tiny_trained_run")

    def evaluate() -> Dict[str, float]:
        config = _background["run"].result()["config"]
        output = root / "eval" / "eval.json"
        output.parent.mkdir()
        tiny_checkpoint.run("ns-eval", "--load-config", config, "--output-path", output, cwd=output.parent)
        return json.loads(output.read_text())["results"]

    def on_the_run(job: Callable[[dict, Path], Any]) -> Any:
        return job(_background["run"].result(), tmp_path_factory.mktemp(job.__name__))

    _background["run"] = worker.submit(tiny_checkpoint.train_tiny, root)
    _background["eval"] = worker.submit(evaluate)
    for job in run_jobs:
        _jobs[job] = worker.submit(on_the_run, job)
    worker.shutdown(wait=False)


BENCH_RUNS = {"decomposition_run": tiny_training.DECOMPOSITION_BENCH}
"""Session fixtures that are one ``seathru-bench run`` each (their arguments), started at collection."""


def _start_bench(name: str, root: Path) -> None:
    worker = ThreadPoolExecutor(1, thread_name_prefix=name)
    _background[name] = worker.submit(tiny_training.bench_run, BENCH_RUNS[name], root)
    worker.shutdown(wait=False)


_jobs: Dict[Callable[..., Any], Future] = {}
"""The futures of the test modules' ``BACKGROUND_JOBS`` and ``TINY_RUN_JOBS``, by job."""


def pytest_collection_finish(session) -> None:
    """Start the tiny run and the bench runs as soon as a collected test needs them: their CLIs run
    on one thread each, the tests meanwhile on the other core; the collected modules'
    ``TINY_RUN_JOBS`` follow the tiny run on its thread. Then queue their ``BACKGROUND_JOBS`` on
    one more thread, in the order their modules run."""
    if session.config.option.collectonly:
        return
    used = set().union(*(set(getattr(item, "fixturenames", ())) for item in session.items))
    for name in BENCH_RUNS:
        if name in used:
            _start_bench(name, session.config._tmp_path_factory.mktemp(name))
    # only modules with a collected test that reads a job (``-m "not slow"`` may have left none)
    modules = dict.fromkeys(item.module for item in session.items if "background_job" in getattr(item, "fixturenames", ()))
    run_jobs = [job for module in modules for job in getattr(module, "TINY_RUN_JOBS", ())]
    if TRAINED_RUN_USERS & used or run_jobs:
        factory = session.config._tmp_path_factory
        _start_in_background(factory.mktemp("tiny_trained_run"), factory, run_jobs)
    jobs = [job for module in modules for job in getattr(module, "BACKGROUND_JOBS", ())]
    if jobs:
        lane = ThreadPoolExecutor(1, thread_name_prefix="background_jobs")
        for job in jobs:
            _jobs[job] = lane.submit(job, session.config._tmp_path_factory.mktemp(job.__name__))
        lane.shutdown(wait=False)


@pytest.fixture(scope="session")
def background_job(tmp_path_factory, request) -> Callable[[Callable[..., Any]], Any]:
    """``background_job(job)``: the result of ``job`` (listed in its module's ``BACKGROUND_JOBS``
    or ``TINY_RUN_JOBS``), waited for; a job that was not started at collection runs here, once."""

    def result(job: Callable[..., Any]) -> Any:
        if job not in _jobs:
            on_the_run = job in getattr(sys.modules[job.__module__], "TINY_RUN_JOBS", ())
            future: Future = Future()
            try:
                folder = tmp_path_factory.mktemp(job.__name__)
                future.set_result(job(request.getfixturevalue("tiny_trained_run"), folder) if on_the_run else job(folder))
            except Exception as error:  # noqa: BLE001 - kept for every test that asks, as a started job's is
                future.set_exception(error)
            _jobs[job] = future
        return _jobs[job].result()

    return result


@pytest.fixture(scope="session")
def decomposition_run(tmp_path_factory) -> dict:
    """``results.json`` of the decomposition check's bench run (``tiny_training.DECOMPOSITION_BENCH``)."""
    if "decomposition_run" not in _background:
        _start_bench("decomposition_run", tmp_path_factory.mktemp("decomposition_run"))
    return _background["decomposition_run"].result()


@pytest.fixture(scope="session")
def tiny_trained_run(tmp_path_factory) -> Dict[str, Path]:
    """``{"root", "scene", "config"}`` of a tiny ``seathru-nerf-lite`` run trained once per
    ``pytest`` run through ``seathru-synth`` and ``ns-train`` (:func:`tiny_checkpoint.train_tiny`),
    started in the background when the tests were collected."""
    if "run" not in _background:  # not seen at collection (requested dynamically)
        _start_in_background(tmp_path_factory.mktemp("tiny_trained_run"), tmp_path_factory)
    return _background["run"].result()


@pytest.fixture(scope="session")
def tiny_run(tiny_trained_run) -> Dict[str, Path]:
    """``tiny_trained_run`` under its older name."""
    return tiny_trained_run


@pytest.fixture(scope="session")
def ns_eval_results(tiny_trained_run) -> Dict[str, float]:
    """``results`` of nerfstudio's ``ns-eval`` CLI on the tiny run (run right after its training)."""
    return _background["eval"].result()


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


BACKGROUND_RESULTS = TRAINED_RUN_USERS | set(BENCH_RUNS) | {"background_job"}
"""The fixtures that wait for a run started in the background at collection."""


def pytest_collection_modifyitems(items) -> None:
    """Mark every test that uses the tiny run ``slow``, and move the modules that wait for a
    background run (:data:`BACKGROUND_RESULTS`) to the end, each whole and in the order
    pytest-randomly gave it (its shuffle runs before this hook): a test that waits early leaves a
    core idle while the rest of the suite could have run beside the background work."""
    for item in items:
        if {"tiny_run", "tiny_trained_run"} & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
    waiting_modules = {item.module for item in items if BACKGROUND_RESULTS & set(getattr(item, "fixturenames", ()))}
    items.sort(key=lambda item: getattr(item, "module", None) in waiting_modules)  # stable: the order within each part stays


def pytest_terminal_summary(terminalreporter, config) -> None:
    """The order's seed, also under ``-q`` (which hides pytest-randomly's header line)."""
    seed = getattr(config.option, "randomly_seed", None)
    if seed is not None and config.getoption("randomly_reorganize", True):
        terminalreporter.write_line(f"test order: pytest-randomly seed {seed} (repeat it with --randomly-seed={seed})")
