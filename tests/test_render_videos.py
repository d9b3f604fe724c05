"""Water on, water off in ``ns-render`` videos (the session's ``tiny_run`` checkpoint).

* ``ns-render interpolate`` renders every output, linear and display, in one call (nerfstudio
  puts several outputs side by side in one video): the expected frame count and size; the
  linear outputs are the linear values, the ``*_display`` ones sRGB encoded, the density maps
  normalised;
* ``ns-render spiral`` works too;
* the real ``ns-render`` CLI renders a camera path (as the viewer's Render tab exports) of
  ``water_split``, ``rgb_display`` and ``clean_display`` in one call: ``water_split``'s left
  half is the video in the water, its right half the clean video, and the two differ.

``ns-render`` runs in-process through its entry point (``ns_render``), and the CLI once, in a
subprocess, as soon as the tiny run is trained (``TINY_RUN_JOBS``). Needs ffmpeg and PyAV.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path
from typing import Dict, Sequence

import numpy as np
import pytest

import tiny_checkpoint
from seathru_nerfstudio.viewer import DISPLAY_OUTPUTS, linear_to_srgb

LINEAR_OUTPUTS = (
    "rgb", "clean", "direct", "backscatter", "depth", "expected_depth", "accumulation",
    "medium_rgb", "medium_attenuation", "medium_backscatter", "prop_depth_0", "prop_depth_1",
)  # fmt: skip
PATH_OUTPUTS = ("water_split", "rgb_display", "clean_display")
PATH_FRAMES, PATH_W, PATH_H = 3, 64, 48
MARGIN = 3
"""Pixels left out at each panel's edges, where the video codec blends neighbouring panels."""


def read_video(path: Path) -> np.ndarray:
    import av

    with av.open(str(path)) as container:
        return np.stack([frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)])


def panels(video: np.ndarray, names: Sequence[str]) -> Dict[str, np.ndarray]:
    """The outputs of a video that ``ns-render`` made of several outputs side by side."""
    width = video.shape[2] // len(names)
    assert width * len(names) == video.shape[2], (video.shape, len(names))
    return {name: video[:, :, i * width : (i + 1) * width] for i, name in enumerate(names)}


def inner(x: np.ndarray) -> np.ndarray:
    return x[..., MARGIN:-MARGIN, MARGIN:-MARGIN, :].astype(np.float64)


def camera_path(scene: Path, run_dir: Path) -> dict:
    """A camera-path JSON (as the viewer's Render tab exports) through the first training
    views, in the dataparser's scene coordinates."""
    transforms = json.loads((scene / "transforms.json").read_text())
    parser = json.loads((run_dir / "dataparser_transforms.json").read_text())
    transform, scale = np.array(parser["transform"]), parser["scale"]
    frames = []
    for frame in transforms["frames"][1 : 1 + PATH_FRAMES]:
        c2w = transform @ np.array(frame["transform_matrix"])
        c2w[:3, 3] *= scale
        frames.append(
            {
                "camera_to_world": np.vstack([c2w, [0, 0, 0, 1]]).reshape(-1).tolist(),
                "fov": math.degrees(2 * math.atan(transforms["h"] / 2 / transforms["fl_y"])),
                "aspect": PATH_W / PATH_H,
            }
        )
    return {
        "render_height": PATH_H,
        "render_width": PATH_W,
        "seconds": 1.0,
        "camera_type": "perspective",
        "camera_path": frames,
    }


@pytest.fixture(scope="module")
def out_dir(tiny_run, tmp_path_factory):
    assert shutil.which("ffmpeg"), "ns-render needs ffmpeg on PATH (apt-get install -y ffmpeg)"
    return tmp_path_factory.mktemp("render")


def camera_path_video(tiny_run: dict, folder: Path) -> dict:
    """The real ns-render CLI rendering the camera path into ``folder``: ``{"returncode",
    "video", "log"}``. Listed in ``TINY_RUN_JOBS``: the suite runs it as soon as the tiny run is
    trained (conftest's ``background_job``)."""
    path = folder / "camera_path.json"
    path.write_text(json.dumps(camera_path(tiny_run["scene"], tiny_run["config"].parent)))
    video, log_path = folder / "cli" / "path.mp4", folder / "ns-render.log"
    with open(log_path, "w") as log:
        proc = tiny_checkpoint.start_group(
            [
                tiny_checkpoint.BIN / "ns-render", "camera-path",
                "--load-config", tiny_run["config"],
                "--camera-path-filename", path,
                "--output-path", video,
                "--rendered-output-names", *PATH_OUTPUTS,
            ],
            cwd=folder, env=tiny_checkpoint.quiet_env(), stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
        try:
            proc.wait(600)
        finally:
            tiny_checkpoint.stop_group(proc)  # its data-manager workers too, if it left any
    return {"returncode": proc.returncode, "video": video, "log": log_path}


TINY_RUN_JOBS = [camera_path_video]


def test_interpolate_renders_every_output_linear_and_display(tiny_run, tiny_pipeline, out_dir, ns_render):
    from nerfstudio.cameras.camera_paths import get_interpolated_camera_path

    names = LINEAR_OUTPUTS + DISPLAY_OUTPUTS
    video_path = out_dir / "interpolate" / "all.mp4"
    ns_render(
        "interpolate", "--load-config", tiny_run["config"], "--output-path", video_path,
        "--rendered-output-names", *names, "--interpolation-steps", 2, "--downscale-factor", 2,
    )  # fmt: skip

    # What the video should hold: the eval cameras' interpolated path, at half resolution.
    pipeline = tiny_pipeline
    cameras = pipeline.datamanager.eval_dataset.cameras
    path = get_interpolated_camera_path(cameras, steps=2, order_poses=False)
    width, height = int(cameras.width[0]) // 2, int(cameras.height[0]) // 2
    video = read_video(video_path)
    assert video.shape == (len(path), height, width * len(names), 3), video.shape
    frames = {name: panel[0] for name, panel in panels(video, names).items()}

    # The first frame is the first eval camera: compare with the model's own render of it.
    first = cameras[0:1].to(pipeline.device)
    first.rescale_output_resolution(0.5)
    pipeline.eval()
    linear = pipeline.model.get_outputs_for_camera(first)
    for name in ("rgb", "clean", "backscatter", "medium_rgb"):
        raw = inner(linear[name].clamp(0, 1).numpy()[None] * 255)
        encoded = inner(linear_to_srgb(linear[name]).numpy()[None] * 255)
        shown, as_is = inner(frames[name + "_display"][None]), inner(frames[name][None])
        # the display version is sRGB encoded (linear data must not look dark) ...
        assert np.abs(shown - encoded).mean() < 6.0, name
        assert np.abs(shown - raw).mean() > np.abs(shown - encoded).mean() + 10.0, name
        # ... and the output itself is the linear value, as every caller gets it
        assert np.abs(as_is - raw).mean() < 6.0, name
    # Medium densities are normalised for display: the largest one shows at full scale.
    for name in ("medium_attenuation_display", "medium_backscatter_display"):
        assert frames[name].max() >= 235, (name, frames[name].max())


def test_spiral(tiny_run, out_dir, ns_render):
    spiral = out_dir / "spiral" / "clean.mp4"
    ns_render(
        "spiral", "--load-config", tiny_run["config"], "--output-path", spiral,
        "--rendered-output-names", "clean_display", "--seconds", 1, "--frame-rate", 3, "--downscale-factor", 2,
    )  # fmt: skip
    video = read_video(spiral)
    assert video.shape[0] == 3 and video.shape[1:3] == (tiny_checkpoint.HEIGHT // 2, tiny_checkpoint.WIDTH // 2), video.shape


@pytest.mark.slow  # reads a TINY_RUN_JOBS result: the tiny run is trained for it
def test_ns_render_cli_water_split_shows_water_left_and_clean_right(background_job):
    rendered = background_job(camera_path_video)
    assert rendered["returncode"] == 0, rendered["log"].read_text()[-5000:]
    video = read_video(rendered["video"])
    assert video.shape == (PATH_FRAMES, PATH_H, PATH_W * len(PATH_OUTPUTS), 3), video.shape
    shown = {name: panel.astype(np.float64) for name, panel in panels(video, PATH_OUTPUTS).items()}
    split, rgb, clean = shown["water_split"], shown["rgb_display"], shown["clean_display"]

    half = PATH_W // 2  # stay clear of the dividing line and of the panels' edges
    left, right = slice(MARGIN, half - MARGIN), slice(half + MARGIN + 1, PATH_W - MARGIN)

    def diff(a, b):
        return float(np.abs(a - b).mean())

    measured = {
        "left_vs_rgb": diff(split[:, :, left], rgb[:, :, left]),
        "right_vs_clean": diff(split[:, :, right], clean[:, :, right]),
        "left_vs_clean": diff(split[:, :, left], clean[:, :, left]),
        "right_vs_rgb": diff(split[:, :, right], rgb[:, :, right]),
    }
    print("water_split differences (mean abs, 0-255):", measured)
    assert measured["left_vs_rgb"] < 6.0 and measured["right_vs_clean"] < 6.0, measured
    assert measured["left_vs_clean"] > 10.0 and measured["right_vs_rgb"] > 10.0, measured  # the water
