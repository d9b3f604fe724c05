"""Issue #4, water on / water off, in ``ns-render`` videos.

* ``ns-render interpolate`` makes a video of every output (``rgb``, ``clean``, ``direct``,
  ``backscatter``, depths, ``accumulation``, the ``medium_*`` maps, ``water_split``) with the
  expected frame count and size; colours are display encoded (sRGB), medium maps normalised;
* ``ns-render spiral`` and ``ns-render camera-path`` work too;
* the real ``ns-render`` CLI renders ``water_split``: its left half is the video in the
  water, its right half the clean video, and the two differ where there is water.

One tiny checkpoint for the module; ``ns-render`` runs in-process through its entry point
(the real CLI once, in a subprocess, in parallel). Needs ffmpeg and PyAV.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent / "browser"))
import tiny_checkpoint  # noqa: E402

pytestmark = pytest.mark.slow

OUTPUTS = (
    "rgb", "clean", "direct", "backscatter", "depth", "expected_depth", "accumulation",
    "medium_rgb", "medium_attenuation", "medium_backscatter", "prop_depth_0", "prop_depth_1",
    "water_split",
)  # fmt: skip
COLOURS = ("rgb", "clean", "direct", "backscatter", "medium_rgb", "water_split")
PATH_FRAMES, PATH_W, PATH_H = 3, 64, 48


def read_video(path: Path) -> np.ndarray:
    import av

    with av.open(str(path)) as container:
        return np.stack([frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)])


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
def trained(tmp_path_factory):
    assert shutil.which("ffmpeg"), "ns-render needs ffmpeg on PATH (apt-get install -y ffmpeg)"
    checkpoint = tiny_checkpoint.train_tiny(tmp_path_factory.mktemp("render"))
    path = checkpoint["root"] / "camera_path.json"
    path.write_text(json.dumps(camera_path(checkpoint["scene"], checkpoint["config"].parent)))
    checkpoint["camera_path"] = path
    return checkpoint


@pytest.fixture(scope="module")
def split_cli(trained):
    """The real ns-render CLI rendering water_split along the camera path, started now so it
    runs while the in-process renders do."""
    root = trained["root"]
    video = root / "cli" / "water_split.mp4"
    log = open(root / "ns-render.log", "w")
    proc = tiny_checkpoint.start_group(
        [
            tiny_checkpoint.BIN / "ns-render", "camera-path",
            "--load-config", trained["config"],
            "--camera-path-filename", trained["camera_path"],
            "--output-path", video,
            "--rendered-output-names", "water_split",
        ],
        cwd=root, env=tiny_checkpoint.quiet_env(), stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    yield {"proc": proc, "video": video, "log": root / "ns-render.log"}
    tiny_checkpoint.stop_group(proc)  # its data-manager workers too, if it left any
    log.close()


@pytest.fixture(scope="module")
def ns_render(trained, split_cli):
    """``ns-render <args>`` in-process, through nerfstudio's own entry point."""
    from nerfstudio.scripts import render

    threads = torch.get_num_threads()
    torch.set_num_threads(1)

    def run(*args) -> None:
        argv = sys.argv
        sys.argv = ["ns-render", *[str(a) for a in args]]
        try:
            render.entrypoint()
        finally:
            sys.argv = argv

    yield run
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def path_videos(trained, ns_render):
    """``ns-render camera-path`` videos of rgb (in water) and clean."""
    videos = {}
    for name in ("rgb", "clean"):
        videos[name] = trained["root"] / "path" / f"{name}.mp4"
        ns_render(
            "camera-path", "--load-config", trained["config"], "--camera-path-filename", trained["camera_path"],
            "--output-path", videos[name], "--rendered-output-names", name,
        )  # fmt: skip
    return videos


def test_interpolate_renders_every_output_to_a_video(trained, ns_render):
    from nerfstudio.cameras.camera_paths import get_interpolated_camera_path
    from nerfstudio.utils.eval_utils import eval_setup

    from seathru_nerfstudio.viewer import linear_to_srgb

    videos = {}
    for name in OUTPUTS:
        videos[name] = trained["root"] / "interpolate" / f"{name}.mp4"
        ns_render(
            "interpolate", "--load-config", trained["config"], "--output-path", videos[name],
            "--rendered-output-names", name, "--interpolation-steps", 2, "--downscale-factor", 2,
        )  # fmt: skip

    # What the videos should hold: the eval cameras' interpolated path, at half resolution.
    _, pipeline, _, _ = eval_setup(trained["config"], test_mode="test")
    cameras = pipeline.datamanager.eval_dataset.cameras
    path = get_interpolated_camera_path(cameras, steps=2, order_poses=False)
    width, height = int(cameras.width[0]) // 2, int(cameras.height[0]) // 2
    frames = {name: read_video(video) for name, video in videos.items()}
    for name, video in frames.items():
        assert video.shape == (len(path), height, width, 3), (name, video.shape)

    # Colours are sRGB-encoded linear radiance (linear data must not look dark): the first
    # frame is the first eval camera.
    first = cameras[0:1].to(pipeline.device)
    first.rescale_output_resolution(0.5)
    pipeline.eval()
    linear = pipeline.model.get_outputs_for_camera(first)  # not a display caller: linear
    for name in ("rgb", "clean", "backscatter", "medium_rgb"):
        shown = frames[name][0].astype(np.float64)
        expected = linear_to_srgb(linear[name]).numpy() * 255
        raw = linear[name].clamp(0, 1).numpy() * 255
        assert np.abs(shown - expected).mean() < 6.0, name
        assert np.abs(shown - raw).mean() > np.abs(shown - expected).mean() + 10.0, name
    # Medium densities are normalised for display: the largest one shows at full scale.
    for name in ("medium_attenuation", "medium_backscatter"):
        assert frames[name][0].max() >= 235, (name, frames[name][0].max())


def test_spiral_and_camera_path(trained, ns_render, path_videos):
    spiral = trained["root"] / "spiral" / "clean.mp4"
    ns_render(
        "spiral", "--load-config", trained["config"], "--output-path", spiral,
        "--rendered-output-names", "clean", "--seconds", 1, "--frame-rate", 3, "--downscale-factor", 2,
    )  # fmt: skip
    video = read_video(spiral)
    assert video.shape[0] == 3 and video.shape[1:3] == (24, 32), video.shape

    for name, path in path_videos.items():
        video = read_video(path)
        assert video.shape == (PATH_FRAMES, PATH_H, PATH_W, 3), (name, video.shape)


def test_ns_render_cli_water_split_shows_water_left_and_clean_right(trained, split_cli, path_videos):
    proc = split_cli["proc"]
    proc.wait(600)
    assert proc.returncode == 0, split_cli["log"].read_text()[-5000:]
    split = read_video(split_cli["video"]).astype(np.float64)
    assert split.shape == (PATH_FRAMES, PATH_H, PATH_W, 3), split.shape

    # Compare with the rgb (in water) and clean videos of the same path.
    rgb = read_video(path_videos["rgb"]).astype(np.float64)
    clean = read_video(path_videos["clean"]).astype(np.float64)
    half, margin = PATH_W // 2, 3  # stay clear of the dividing line and codec bleeding
    left, right = slice(0, half - margin), slice(half + margin + 1, PATH_W)

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
