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

    ns_render(
        "dataset", "--load-config", tiny_run["config"], "--split", "test",
        "--rendered-output-names", "clean_display", "depth", "--output-path", tmp_path, "--image-format", "png",
    )  # fmt: skip
    clean = sorted((tmp_path / "test" / "clean_display").rglob("*.png"))
    depth = sorted((tmp_path / "test" / "depth").rglob("*.png"))
    assert clean and [p.name for p in clean] == [p.name for p in depth]  # one image per held-out view
    first_clean, first_depth = iio.imread(clean[0])[..., :3], iio.imread(depth[0])[..., :3]
    assert first_clean.shape == first_depth.shape == (tiny_checkpoint.HEIGHT, tiny_checkpoint.WIDTH, 3)
    assert first_clean.std() > 0 and first_depth.std() > 0
    assert np.abs(first_clean.astype(float) - first_depth).mean() > 5
