"""Fault injection (issue 37): every bad input, and every way a run is stopped, as a user meets it.

Each case breaks a copy of one tiny ``seathru-synth`` scene (32×24, 6 views) and runs our or
nerfstudio's command on it. It asserts what the user sees: the exit status, one ``Error:`` line
that names the file (the frame, the option) and says what to do, no traceback, and no process of
the run left alive afterwards.

The cases that stop at set-up run the commands' entry points through :mod:`forked_cli` (a fork
server that has imported nerfstudio once: ~10 s saved per case). The cases about processes run
the installed console scripts themselves, in the background from the start of the suite
(``BACKGROUND_JOBS``), while the other tests run: a run that finishes (no staging folder left), the viewer on it
(no data-loading worker: nothing trains) stopped with SIGTERM,
ns-train killed with SIGKILL (its data-loading worker must go too), and the data-loading worker
killed under a training run (the run must end with that error instead of waiting forever).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Dict, List

import cv2
import numpy as np
import psutil
import pytest

import forked_cli
from tiny_training import BIN, TINY_MODEL_ARGS, make_scene

pytestmark = pytest.mark.slow  # runs nerfstudio's commands

NS_TRAIN_ARGS = ["seathru-nerf-lite", "--data", "scene", "--output-dir", "out", "--max-num-iterations", "3", *TINY_MODEL_ARGS]


# ------------------------------------------------------------------------------ the scene
@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """One tiny scene for the module, written by the real ``seathru-synth`` command."""
    root = tmp_path_factory.mktemp("faults")
    subprocess.run(
        [str(BIN / "seathru-synth"), "--output-dir", str(root / "scene"), "--width", "32", "--height", "24", "--num-views", "6"],
        check=True, capture_output=True,
    )  # fmt: skip
    return root / "scene"


def case(scene: Path, tmp_path: Path) -> Path:
    """A folder holding a copy of the scene as ``scene/``: a case breaks its copy only."""
    shutil.copytree(scene, tmp_path / "scene")
    return tmp_path / "scene"


def transforms(folder: Path) -> dict:
    return json.loads((folder / "transforms.json").read_text())


def write_transforms(folder: Path, meta: dict) -> None:
    (folder / "transforms.json").write_text(json.dumps(meta, indent=2))


def assert_one_line_error(result: forked_cli.Result, *named: str, returncode: int = 1) -> str:
    """Exit status ``returncode``, no traceback, no process left, and exactly one ``Error:`` line,
    which holds every string of ``named``; returns that line."""
    assert result.returncode == returncode, result.output[-3000:]
    assert "Traceback" not in result.output, result.output[-3000:]
    assert result.stray == [], result.stray
    (line,) = result.error_lines() or [""]
    for name in named:
        assert name in line, f"{name!r} not in {line!r}\n{result.output[-2000:]}"
    return line


# ------------------------------------------------------------------------- background runs
def children_of(pid: int) -> List[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def data_worker(pid: int) -> psutil.Process | None:
    """The nerfstudio data-loading worker under process ``pid`` (not multiprocessing's resource tracker)."""
    for child in children_of(pid):
        try:
            if "spawn_main" in " ".join(child.cmdline()) and "resource_tracker" not in " ".join(child.cmdline()):
                return child
        except psutil.Error:
            pass
    return None


def start(args: List[str], cwd: Path, log: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.Popen(args, cwd=cwd, stdout=open(cwd / log, "w"), stderr=subprocess.STDOUT, env=env)


def wait_for(condition, process: subprocess.Popen, what: str, timeout_s: float = 300.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert process.poll() is None, f"exited ({process.returncode}) before {what}"
        assert time.monotonic() < deadline, f"no {what} after {timeout_s} s"
        time.sleep(0.1)


def gone_within(processes: List[psutil.Process], seconds: float) -> List[str]:
    """Those of ``processes`` still alive after ``seconds`` (then killed)."""
    _, alive = psutil.wait_procs(processes, timeout=seconds)
    left = forked_cli.describe(alive)
    for process in alive:
        process.kill()
    return left


def finished_run_then_viewer(root: Path) -> Dict:
    """A run to its end (and its leftovers); then the viewer on it, stopped with SIGTERM."""
    trainer = start([str(BIN / "ns-train"), *NS_TRAIN_ARGS, "--timestamp", "done", "--experiment-name", "x"], root, "train.log")
    returncode = trainer.wait(600)
    run_dir = root / "out" / "x" / "seathru-nerf-lite" / "done"
    result = {"returncode": returncode, "log": (root / "train.log").read_text(), "run_dir": run_dir}
    result["left_in_run_dir"] = sorted(p.name for p in run_dir.iterdir()) if run_dir.is_dir() else []
    viewer = start([str(BIN / "seathru-viewer"), "--load-config", str(run_dir / "config.yml")], root, "viewer.log")
    try:
        # viser's banner: the model is loaded and the viewer serves
        wait_for(lambda: "ws://" in (root / "viewer.log").read_text(errors="replace"), viewer, "the viewer's start")
        result["viewer_data_worker"] = data_worker(viewer.pid)
        family = children_of(viewer.pid)
        viewer.send_signal(signal.SIGTERM)
        viewer.wait(60)
        result["viewer_left"] = gone_within(family, 10.0)
    finally:
        if viewer.poll() is None:
            viewer.kill()
    return result


def sigkill_trainer(root: Path) -> Dict:
    """ns-train SIGKILLed mid-run, as in the kill-and-resume workflow; what it leaves alive."""
    trainer = start([str(BIN / "ns-train"), *NS_TRAIN_ARGS, "--max-num-iterations", "100000", "--steps-per-save", "1"], root, "train.log")
    try:
        wait_for(lambda: list(root.glob("out/**/step-*.ckpt")), trainer, "checkpoint")
        family = children_of(trainer.pid)
        os.kill(trainer.pid, signal.SIGKILL)  # the trainer only, as `kill -9 PID` does
        trainer.wait(60)
        return {"family": [p.pid for p in family], "left": gone_within(family, 10.0)}
    finally:
        if trainer.poll() is None:
            trainer.kill()


def kill_worker(root: Path) -> Dict:
    """The data-loading worker SIGKILLed under a training run (as the OOM killer would)."""
    trainer = start([str(BIN / "ns-train"), *NS_TRAIN_ARGS, "--max-num-iterations", "100000", "--steps-per-save", "1"], root, "train.log")
    try:
        wait_for(lambda: list(root.glob("out/**/step-*.ckpt")), trainer, "checkpoint")
        family = children_of(trainer.pid)
        worker = data_worker(trainer.pid)
        worker.kill()
        started = time.monotonic()
        returncode = trainer.wait(120)
        return {
            "returncode": returncode,
            "seconds": time.monotonic() - started,
            "worker": worker.pid,
            "log": forked_cli.ANSI.sub("", (root / "train.log").read_text()),
            "left": gone_within(family, 10.0),
        }
    finally:
        if trainer.poll() is None:
            trainer.kill()


def process_cases(root: Path) -> Dict[str, Dict]:
    """The process cases side by side, each on its own copy of a tiny scene; their results by name.
    Listed in ``BACKGROUND_JOBS``: the suite starts it at collection (conftest's ``background_job``)."""
    scene = make_scene(root / "original")
    cases = {"finished": finished_run_then_viewer, "sigkill": sigkill_trainer, "worker": kill_worker}
    with ThreadPoolExecutor(max_workers=len(cases)) as pool:
        futures = {}
        for name, job in cases.items():
            shutil.copytree(scene, root / name / "scene")
            futures[name] = pool.submit(job, root / name)
        return {name: future.result() for name, future in futures.items()}


BACKGROUND_JOBS = [process_cases]


@pytest.fixture(scope="module")
def background(background_job) -> Dict[str, Dict]:
    """The results of :func:`process_cases`."""
    return background_job(process_cases)


# -------------------------------------------------------------------------- data at set-up
def test_seathru_synth_output_follows_the_umask(scene) -> None:
    mask = os.umask(0o022)
    os.umask(mask)
    for path in (scene, scene / "images"):
        assert path.stat().st_mode & 0o777 == 0o777 & ~mask, path
    assert (scene / "transforms.json").stat().st_mode & 0o777 == 0o666 & ~mask


def test_an_image_of_another_size(scene, tmp_path) -> None:
    data = case(scene, tmp_path)
    image = cv2.imread(str(data / "images/frame_00001.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(data / "images/frame_00001.png"), cv2.resize(image, (40, 30)))
    result = forked_cli.run("ns-train", *NS_TRAIN_ARGS, cwd=tmp_path)
    assert_one_line_error(result, "images/frame_00001.png", "40×30", "32×24")


def test_nan_pixels_in_a_float_tiff(scene, tmp_path) -> None:
    from PIL import Image

    data = case(scene, tmp_path)
    grey = cv2.imread(str(data / "images/frame_00002.png"), cv2.IMREAD_UNCHANGED).astype(np.float32).mean(-1) / 65535
    grey[3, 4] = np.nan
    Image.fromarray(grey, mode="F").save(data / "images/frame_00002.tif")  # float32 TIFF, NaN kept
    (data / "images/frame_00002.png").unlink()
    meta = json.loads((data / "transforms.json").read_text().replace("images/frame_00002.png", "images/frame_00002.tif"))
    write_transforms(data, meta)
    result = forked_cli.run("ns-train", *NS_TRAIN_ARGS, cwd=tmp_path)
    assert_one_line_error(result, "images/frame_00002.tif", "NaN", "row 3, column 4")


@pytest.mark.parametrize("value, word", [(0, "all black"), (65535, "all white")])
def test_an_all_black_or_all_white_image(scene, tmp_path, value, word) -> None:
    data = case(scene, tmp_path)
    cv2.imwrite(str(data / "images/frame_00003.png"), np.full((24, 32, 3), value, np.uint16))
    result = forked_cli.run("ns-train", *NS_TRAIN_ARGS, cwd=tmp_path)
    assert_one_line_error(result, "images/frame_00003.png", word)


def test_invalid_transforms_json(scene, tmp_path) -> None:
    data = case(scene, tmp_path)
    lines = (data / "transforms.json").read_text().splitlines()
    end_of_pose = next(i for i, line in enumerate(lines) if line.strip() == "],")  # the first row of frame 0's pose ends
    lines[end_of_pose] = lines[end_of_pose].replace("],", "]")  # the comma after it forgotten
    broken = "\n".join(lines)
    (data / "transforms.json").write_text(broken)
    with pytest.raises(json.JSONDecodeError) as parsed:
        json.loads(broken)
    result = forked_cli.run("ns-train", *NS_TRAIN_ARGS, cwd=tmp_path)
    assert_one_line_error(result, "scene/transforms.json", f"line {parsed.value.lineno} column {parsed.value.colno}")


def test_nan_in_a_transform_matrix(scene, tmp_path) -> None:
    data = case(scene, tmp_path)
    meta = transforms(data)
    meta["frames"][2]["transform_matrix"][0][3] = float("nan")
    write_transforms(data, meta)
    result = forked_cli.run("ns-train", *NS_TRAIN_ARGS, cwd=tmp_path)
    assert_one_line_error(result, "scene/transforms.json", "frame 2 (images/frame_00002.png)", "transform_matrix[0][3]")


def test_zero_frames(scene, tmp_path) -> None:
    data = case(scene, tmp_path)
    meta = transforms(data)
    meta.update(frames=[], train_filenames=[], val_filenames=[], test_filenames=[])
    write_transforms(data, meta)
    result = forked_cli.run("ns-train", *NS_TRAIN_ARGS, cwd=tmp_path)
    assert_one_line_error(result, "scene/transforms.json", "no frames")


def test_a_missing_depth_file(scene, tmp_path) -> None:
    data = case(scene, tmp_path)
    (data / "depth/frame_00004.png").unlink()
    result = forked_cli.run("ns-train", *NS_TRAIN_ARGS, cwd=tmp_path)
    assert_one_line_error(result, "frame 4 (images/frame_00004.png)", "depth_file_path depth/frame_00004.png")


# ------------------------------------------------------------------------ options, checkpoints
@pytest.mark.parametrize(
    "option, value",
    [("--pipeline.model.medium-fit-step", "-5"), ("--pipeline.model.research.medium-oracle", "/nonexistent.json")],
)
def test_a_bad_model_option(scene, tmp_path, option, value) -> None:
    """Refused by the model config's check while tyro parses the command line: tyro's usage error
    (exit status 2) with the option and the value, no traceback."""
    case(scene, tmp_path)
    result = forked_cli.run("ns-train", *NS_TRAIN_ARGS, option, value, cwd=tmp_path)
    assert result.returncode == 2, result.output[-3000:]
    assert "Traceback" not in result.output and result.stray == []
    assert option in result.output and value in result.output, result.output[-3000:]


@pytest.fixture(scope="module")
def run_without_checkpoint(scene, tmp_path_factory) -> Path:
    """A run's ``config.yml`` whose ``nerfstudio_models/`` is empty (stopped before its first save)."""
    from tiny_training import tiny_config

    config = tiny_config(scene, tmp_path_factory.mktemp("empty_run") / "outputs", iterations=3)
    config.save_config()
    config.get_checkpoint_dir().mkdir(parents=True)
    return config.get_base_dir() / "config.yml"


@pytest.mark.parametrize("command, subcommand, output", [("ns-eval", [], "eval.json"), ("ns-render", ["interpolate"], "video.mp4")])
def test_eval_or_render_a_run_whose_checkpoint_folder_is_empty(run_without_checkpoint, tmp_path, command, subcommand, output) -> None:
    args = [*subcommand, "--load-config", run_without_checkpoint, "--output-path", output]
    result = forked_cli.run(command, *args, cwd=tmp_path)
    folder = run_without_checkpoint.parent / "nerfstudio_models"
    assert_one_line_error(result, str(folder), "holds no step-*.ckpt")


# ---------------------------------------------------------------------- seathru-process-data
def writable(folder: Path) -> bool:
    """Whether a folder can be made in ``folder`` (``os.access`` says yes to root everywhere)."""
    import tempfile

    try:
        Path(tempfile.mkdtemp(dir=folder)).rmdir()
    except OSError:
        return False
    return True


def test_process_data_into_a_read_only_parent(scene, tmp_path) -> None:
    parent = tmp_path / "read_only"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        if writable(parent):  # root writes anywhere: a file system that takes no new folders instead
            parent = next((p for p in (Path("/sys"), Path("/proc")) if p.is_dir() and not writable(p)), None)
            assert parent is not None, "found no folder to test with: /sys and /proc both take new folders"
        result = forked_cli.run("seathru-process-data", "--data", scene / "images", "--output-dir", parent / "dataset", cwd=tmp_path)
    finally:
        (tmp_path / "read_only").chmod(0o755)
    assert_one_line_error(result, f"--output-dir {parent / 'dataset'}", "not writable")
    assert not list((tmp_path / "read_only").iterdir())


def test_process_data_on_identical_images(scene, tmp_path) -> None:
    captures = tmp_path / "captures"
    captures.mkdir()
    for k in range(3):
        shutil.copy(scene / "images/frame_00001.png", captures / f"shot_{k}.png")
    result = forked_cli.run("seathru-process-data", "--data", captures, "--output-dir", tmp_path / "dataset", cwd=tmp_path)
    assert_one_line_error(result, "shot_0.png = shot_1.png = shot_2.png", "camera to move")
    assert not (tmp_path / "dataset").exists()


def test_process_data_below_the_minimum_registered_fraction(scene, tmp_path) -> None:
    """Half the folder is a second, unrelated scene: the best model cannot hold more than the
    other half, which a minimum of 0.9 refuses, naming the input folder (not a scratch folder)."""
    from seathru_nerfstudio.data.synthetic import SynthConfig, generate

    captures = tmp_path / "captures"
    for seed, preset in ((3, "water"), (11, "fog")):
        generated = generate(SynthConfig(output_dir=tmp_path / preset, preset=preset, seed=seed, width=160, height=120, num_views=8, sfm_points_per_view=0))
        for path in (generated / "images").iterdir():
            captures.mkdir(exist_ok=True)
            shutil.copy(path, captures / f"{preset}_{path.name}")
    result = forked_cli.run(
        "seathru-process-data", "--data", captures, "--output-dir", tmp_path / "dataset", "--min-registered-fraction", "0.9",
        "--white-balance", "none", "--camera-model", "PINHOLE", cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(result, f"of the 16 images of {captures}", "--min-registered-fraction 0.9")
    assert not (tmp_path / "dataset").exists()


# ------------------------------------------------------------------------------- processes
def test_a_finished_run_leaves_no_staging_folder(background) -> None:
    result = background["finished"]
    assert result["returncode"] == 0, result["log"][-3000:]
    assert sorted(p.name for p in (result["run_dir"] / "nerfstudio_models").iterdir()) == ["step-000000002.ckpt"]
    assert not [name for name in result["left_in_run_dir"] if name.startswith(".")], result["left_in_run_dir"]


def test_the_viewer_of_a_finished_run_starts_no_data_worker_and_sigterm_leaves_no_process(background) -> None:
    """Nothing trains there, so no training rays are sampled (``data/datamanager.py``)."""
    assert background["finished"]["viewer_data_worker"] is None
    assert background["finished"]["viewer_left"] == []


def test_sigkill_of_ns_train_leaves_no_process(background) -> None:
    result = background["sigkill"]
    assert len(result["family"]) >= 1  # the data-loading worker at least
    assert result["left"] == []


def test_a_killed_data_worker_ends_the_run_with_its_error(background) -> None:
    result = background["worker"]
    assert result["returncode"] == 1, result["log"][-3000:]
    assert "Traceback" not in result["log"]
    (line,) = [line for line in result["log"].splitlines() if line.startswith("Error:")]
    assert f"data-loading worker (pid {result['worker']}) ended with signal 9 (SIGKILL)" in line
    assert result["left"] == []
    print(f"the trainer stopped {result['seconds']:.1f} s after its worker was killed")


def test_a_worker_that_meets_a_bad_file_ends_the_run_naming_it(scene, tmp_path) -> None:
    """An image that disappears after the load-time check: the worker's error (naming the file)
    reaches the trainer's ``next_train``, in place of a wait that never ends."""
    from seathru_nerfstudio.data.datamanager import SeathruDataManager
    from seathru_nerfstudio.input_errors import InputError
    from tiny_training import tiny_config

    data = case(scene, tmp_path)
    config = tiny_config(data, tmp_path / "out", iterations=3).pipeline.datamanager
    manager = config.setup(device="cpu", test_mode="val")  # starts the worker, which first imports for seconds
    try:
        assert isinstance(manager, SeathruDataManager)
        (data / "images/frame_00001.png").unlink()
        with pytest.raises(InputError, match="images/frame_00001.png: no such image file"):
            manager.next_train(0)
        (worker,) = manager.data_procs
        worker.join(10)
        assert worker.exitcode == 1
    finally:
        for worker in manager.data_procs:
            worker.kill()
