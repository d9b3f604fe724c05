"""When the data manager starts its data-loading workers (``data/datamanager.py``): a trainer's at
once, one built to evaluate (``ns-eval``, ``ns-render``, ``ns-export``, ``ns-viewer``,
``seathru-medium``: ``eval_setup``'s ``test_mode="test"``) only when a training batch is asked
for; and no run without a worker, which would wait for its first batch forever."""

from __future__ import annotations

from pathlib import Path

import psutil
import pytest

from tiny_training import make_scene, tiny_config


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return make_scene(tmp_path_factory.mktemp("workers"))


SPAWNED_ENTRIES = ("multiprocess.spawn import spawn_main", "multiprocess.resource_tracker import main")
"""What the command line of a process that ``multiprocess`` spawns holds (pathos's fork of
``multiprocessing``, which nerfstudio's data manager and ours use): a worker, or the resource
tracker that the first queue starts. The standard library's processes name ``multiprocessing.…``
instead, which these do not match."""


def _children() -> set:
    """This process's direct children: a worker the data manager starts is one."""
    return {child.pid for child in psutil.Process().children()}


def _spawned_children() -> set:
    """This process's direct children that ``multiprocess`` spawned (nerfstudio's data manager sets
    the ``spawn`` start method). The suite's background threads (``conftest``: the tiny run, the bench
    runs, their jobs) start processes at any moment: CLIs, and the standard library's fork server of
    ``forked_cli`` with its resource tracker, which are direct children too. They are told apart by
    their command line; the CLIs that fork server starts are grandchildren."""
    pids = set()
    for child in psutil.Process().children():
        try:
            command = " ".join(child.cmdline())
        except psutil.Error:  # ended, or a zombie, since it was listed
            continue
        if any(entry in command for entry in SPAWNED_ENTRIES):
            pids.add(child.pid)
    return pids


def _stop(manager) -> None:
    for worker in manager.data_procs:
        worker.kill()
        worker.join(10)


def test_a_data_manager_built_to_evaluate_starts_its_worker_at_the_first_training_batch(scene, tmp_path) -> None:
    config = tiny_config(scene, tmp_path / "out", iterations=3).pipeline.datamanager
    before = _spawned_children()
    manager = config.setup(device="cpu", test_mode="test")
    try:
        assert manager.data_procs == []
        assert _spawned_children() - before == set()  # nothing started, not even multiprocessing's helpers
        bundle, batch = manager.next_train(0)  # asked for anyway: it comes, from a worker
        (worker,) = manager.data_procs
        assert worker.is_alive() and worker.pid in _children()
        assert bundle.origins.shape == (config.train_num_rays_per_batch, 3)
        assert batch["image"].shape[0] == config.train_num_rays_per_batch
    finally:
        _stop(manager)


def test_a_trainers_data_manager_starts_its_worker_when_built(scene, tmp_path) -> None:
    config = tiny_config(scene, tmp_path / "out", iterations=3).pipeline.datamanager
    manager = config.setup(device="cpu", test_mode="val")
    try:
        (worker,) = manager.data_procs
        assert worker.pid in _children()  # started before any batch is asked for: its imports overlap the set-up
    finally:
        _stop(manager)


@pytest.mark.parametrize("count", [0, -1])
def test_no_worker_is_an_input_error_naming_the_option(scene, tmp_path, count) -> None:
    from seathru_nerfstudio.input_errors import InputError

    config = tiny_config(scene, tmp_path / "out", iterations=3).pipeline.datamanager
    config.num_processes = count
    with pytest.raises(InputError, match=f"--pipeline.datamanager.num-processes {count}: at least one"):
        config.setup(device="cpu", test_mode="val")
