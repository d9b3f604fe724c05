"""End to end through the real CLIs: seathru-synth -> ns-train -> ns-eval -> ns-render."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BIN = Path(sys.executable).parent
ITERATIONS = 60


def run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    result = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, f"{args[0]} failed:\n{result.stdout[-3000:]}\n{result.stderr[-5000:]}"
    return result


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("e2e")
    scene = root / "scene"
    run(BIN / "seathru-synth", "--output-dir", scene, "--width", "48", "--height", "36", "--num-views", "6", cwd=root)
    run(
        BIN / "ns-train", "seathru-nerf-lite",
        "--data", scene,
        "--output-dir", root / "outputs",
        "--max-num-iterations", str(ITERATIONS),
        "--steps-per-save", str(ITERATIONS),
        "--steps-per-eval-batch", "1000",
        "--steps-per-eval-image", "1000",
        "--logging.steps-per-log", "1",
        "--pipeline.datamanager.train-num-rays-per-batch", "512",
        "--vis", "tensorboard",
        cwd=root,
    )  # fmt: skip
    (config,) = list((root / "outputs").glob("*/seathru-nerf-lite/*/config.yml"))
    return {"root": root, "scene": scene, "config": config}


def train_losses(run_dir: Path) -> np.ndarray:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events,) = list(run_dir.glob("events.out.tfevents.*"))
    accumulator = EventAccumulator(str(events))
    accumulator.Reload()
    return np.array([event.value for event in accumulator.Scalars("Train Loss")])


def test_training_writes_a_checkpoint_and_the_loss_goes_down(trained):
    run_dir = trained["config"].parent
    assert list((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    losses = train_losses(run_dir)
    assert len(losses) >= ITERATIONS - 5 and np.isfinite(losses).all()
    assert losses[-10:].mean() < 0.5 * losses[:5].mean(), losses


def test_ns_eval_reports_finite_in_medium_clean_and_depth_metrics(trained):
    output = trained["root"] / "eval.json"
    run(BIN / "ns-eval", "--load-config", trained["config"], "--output-path", output, cwd=trained["root"])
    results = json.loads(output.read_text())["results"]
    for key in ("psnr", "ssim", "clean_psnr", "clean_ssim", "depth_abs_rel", "depth_abs_rel_far"):
        assert key in results and np.isfinite(results[key]), key
    assert results["psnr"] > 10


def test_ns_render_clean_video_and_images(trained):
    import av

    assert shutil.which("ffmpeg"), "ns-render needs ffmpeg on PATH (scripts/setup.sh installs it)"

    root = trained["root"]
    video = root / "renders" / "clean.mp4"
    common = ("--load-config", trained["config"], "--rendered-output-names", "clean", "--interpolation-steps", "2")
    run(BIN / "ns-render", "interpolate", *common, "--output-path", video, "--frame-rate", "4", cwd=root)
    with av.open(str(video)) as container:
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
    # interpolate: interpolation_steps frames between each pair of consecutive eval poses (2 eval views)
    assert len(frames) == 2 and frames[0].shape[:2] == (36, 48)
    images = root / "renders" / "clean_frames"
    run(BIN / "ns-render", "interpolate", *common, "--output-path", images, "--output-format", "images",
        "--image-format", "png", cwd=root)  # fmt: skip
    pngs = sorted(images.glob("*.png"))
    assert len(pngs) == 2
    import imageio.v3 as iio

    frame = iio.imread(pngs[0])
    assert frame.shape[:2] == (36, 48) and np.isfinite(frame).all() and frame.std() > 0
