"""End to end through the real CLIs: seathru-synth -> ns-train (``tiny_run``, once per session)
-> ns-eval (``ns_eval_results``) -> ns-render (its entry point in-process; the CLI itself and
videos of every output: ``test_render_videos.py``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import tiny_checkpoint


def train_losses(run_dir: Path) -> np.ndarray:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events,) = list(run_dir.glob("events.out.tfevents.*"))
    accumulator = EventAccumulator(str(events))
    accumulator.Reload()
    return np.array([event.value for event in accumulator.Scalars("Train Loss")])


def test_training_writes_a_checkpoint_and_the_loss_goes_down(tiny_run):
    run_dir = tiny_run["config"].parent
    assert list((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    losses = train_losses(run_dir)
    assert len(losses) >= tiny_checkpoint.ITERATIONS - 5 and np.isfinite(losses).all()
    assert losses[-10:].mean() < 0.5 * losses[:5].mean(), losses


def test_ns_eval_reports_finite_in_medium_clean_and_depth_metrics(ns_eval_results):
    for key in ("psnr", "ssim", "clean_psnr", "clean_ssim", "depth_abs_rel", "depth_abs_rel_far"):
        assert key in ns_eval_results and np.isfinite(ns_eval_results[key]), key
    assert ns_eval_results["psnr"] > 10


def test_ns_render_writes_images_of_several_outputs_in_one_call(tiny_run, tmp_path, ns_render):
    import imageio.v3 as iio

    images = tmp_path / "frames"
    ns_render(
        "interpolate", "--load-config", tiny_run["config"],
        "--rendered-output-names", "clean_display", "depth", "--interpolation-steps", "2",
        "--output-path", images, "--output-format", "images", "--image-format", "png",
    )  # fmt: skip
    pngs = sorted(images.glob("*.png"))
    # interpolate: interpolation_steps frames between each pair of consecutive eval poses
    assert len(pngs) >= 2
    frame = iio.imread(pngs[0])
    assert frame.shape[:2] == (48, 2 * 64)  # the two outputs side by side
    clean, depth = frame[:, :64, :3], frame[:, 64:, :3]
    assert clean.std() > 0 and depth.std() > 0 and np.abs(clean.astype(float) - depth).mean() > 5
