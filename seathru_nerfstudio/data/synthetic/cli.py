"""``seathru-synth``: write a synthetic scene (see :mod:`seathru_nerfstudio.data.synthetic`)."""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from nerfstudio.utils.rich_utils import CONSOLE, get_progress
from seathru_nerfstudio.data.ground_truth import FRAME_FIELDS, GT_CLEAN_FILENAMES, GT_DEPTH_FILENAMES
from seathru_nerfstudio.data.io import OutputFolderError, atomic_output_folder, write_png16, write_png16_gray
from seathru_nerfstudio.data.synthetic.cameras import HORIZONTAL_FOV_DEG, intrinsics, make_poses
from seathru_nerfstudio.data.synthetic.render import PRESETS, PresetName, render_view, sfm_like_depth
from seathru_nerfstudio.data.synthetic.scene import GEOMETRY, Geometry, build_scene
from seathru_nerfstudio.quiet import silence_upstream_warnings

HOLDOUT_EVERY = 5
"""Views 0, 5, 10, ... are held out for val/test."""


class SynthError(ValueError):
    """The options cannot describe a scene."""


@dataclass
class SynthConfig:
    """Generate a synthetic forward-facing multi-view scene seen through water or fog."""

    output_dir: Path
    """Folder to create (must not exist or be empty, unless --overwrite)."""
    preset: PresetName = "water"
    """Medium: 'water' (paper's Fern simulation), 'turbid' (green coastal water, objects ~1-8 m),
    'fog' (grey, beta=1.2/m) or 'none' (clear)."""
    seed: int = 0
    """Random seed for scene layout, textures and camera jitter; same seed = identical files."""
    width: int = 160
    """Image width in pixels."""
    height: int = 120
    """Image height in pixels."""
    num_views: int = 20
    """Number of views; every 5th view (0, 5, 10, ...) is held out for val/test."""
    overwrite: bool = False
    """Replace the output folder if it exists and is non-empty."""
    supersample: int = 2
    """Anti-aliasing: supersample^2 rays per pixel, medium applied per ray; 1 = off (exact model per pixel)."""
    sfm_points_per_view: int = 300
    """Sparse depth like structure-from-motion's: this many textured pixels per view get their
    true z-depth in ``depth/`` (nerfstudio's ``depth_file_path``, 16-bit millimetres, 0 =
    unknown); 0: none. Open water and flat texture have no SfM points, as in a real capture."""
    rig_depth: float = 0.0
    """Metres over which the cameras also step back from the scene along the rig's axis (0: a flat
    forward-facing rig). The attenuation is determined by the range differences between views, so
    this makes it easier to find: with 1 m, training found all nine medium values within 12%, where
    the flat rig leaves β_D 20–30% high (docs/history.md, 2026-11-25)."""


def _validate(config: SynthConfig) -> None:
    if config.preset not in PRESETS:
        raise SynthError(f"unknown preset {config.preset!r}; choose from {sorted(PRESETS)}")
    if config.width < 8 or config.height < 8:
        raise SynthError("--width and --height must be at least 8 pixels")
    if config.num_views < 2:
        raise SynthError("--num-views must be at least 2 (view 0 is held out)")
    if config.supersample < 1:
        raise SynthError("--supersample must be >= 1")
    if not (0.0 <= config.rig_depth <= 10.0):
        raise SynthError("--rig-depth must be between 0 and 10 metres")


def generate(config: SynthConfig) -> Path:
    """Render the scene described by ``config`` into ``config.output_dir`` and return that path.

    Raises :class:`SynthError` on bad options and ``OutputFolderError`` (naming the folder) if
    the folder holds files and ``config.overwrite`` is False; nothing is written then.
    """
    _validate(config)
    out = Path(config.output_dir).expanduser().absolute()
    start = time.perf_counter()

    w, h, n_views, ss = config.width, config.height, config.num_views, config.supersample
    medium = {k: np.asarray(v, dtype=np.float64) for k, v in PRESETS[config.preset].items()}
    rng_scene = np.random.default_rng([config.seed, 1])
    rng_cams = np.random.default_rng([config.seed, 2])
    geometry = dataclasses.replace(GEOMETRY.get(config.preset, Geometry()), rig_depth=config.rig_depth)
    scene = build_scene(rng_scene, geometry)
    poses = make_poses(rng_cams, n_views, geometry)
    K = intrinsics(w, h)

    with atomic_output_folder(out, config.overwrite) as tmp:
        folders = ["images", "ground_truth/clean", "ground_truth/depth"] + ["depth"] * (config.sfm_points_per_view > 0)
        for folder in folders:
            (tmp / folder).mkdir(parents=True)
        frames = []
        names = []
        n_open = 0
        progress = get_progress(f"[bold yellow]seathru-synth: {config.preset} {w}x{h}", suffix="views/s")
        with progress:
            task = progress.add_task("views", total=n_views)
            # Views are independent; numpy releases the GIL, so two threads use both cores.
            # Results come back in view order, so the output does not depend on scheduling.
            render = lambda c2w: render_view(scene, c2w, K, w, h, ss, medium)  # noqa: E731
            with ThreadPoolExecutor(max_workers=max(1, min(2, os.cpu_count() or 1))) as pool:
                for i, (I, J, depth) in enumerate(pool.map(render, list(poses))):
                    stem = f"frame_{i:05d}"
                    name = f"images/{stem}.png"
                    frame = {"file_path": name, "transform_matrix": poses[i].tolist()}
                    if config.sfm_points_per_view > 0:
                        frame["depth_file_path"] = f"depth/{stem}.png"
                        sparse = sfm_like_depth(J, depth, K, config.sfm_points_per_view, seed=(config.seed, i))
                        write_png16_gray(tmp / frame["depth_file_path"], sparse)
                    frame[FRAME_FIELDS[GT_CLEAN_FILENAMES]] = f"ground_truth/clean/{stem}.png"
                    frame[FRAME_FIELDS[GT_DEPTH_FILENAMES]] = f"ground_truth/depth/{stem}.npy"
                    write_png16(tmp / name, I)
                    write_png16(tmp / frame[FRAME_FIELDS[GT_CLEAN_FILENAMES]], J)
                    np.save(tmp / frame[FRAME_FIELDS[GT_DEPTH_FILENAMES]], depth)
                    n_open += int(np.sum(~np.isfinite(depth)))
                    frames.append(frame)
                    names.append(name)
                    progress.advance(task)

        held = [names[i] for i in range(n_views) if i % HOLDOUT_EVERY == 0]
        train = [names[i] for i in range(n_views) if i % HOLDOUT_EVERY != 0]
        transforms = {
            "camera_model": "OPENCV",
            **K,
            "w": w,
            "h": h,
            "k1": 0.0,
            "k2": 0.0,
            "p1": 0.0,
            "p2": 0.0,
            "frames": frames,
            "train_filenames": train,
            "val_filenames": held,
            "test_filenames": held,
        }
        (tmp / "transforms.json").write_text(json.dumps(transforms, indent=2) + "\n")
        med = {
            "preset": config.preset,
            "beta_D": medium["beta_D"].tolist(),
            "beta_B": medium["beta_B"].tolist(),
            "B_inf": medium["B_inf"].tolist(),
            "units": "1/m",
            "world_units": "m",
            "color_space": "linear",
            "image_formation": "I = J*exp(-beta_D*z) + B_inf*(1-exp(-beta_B*z)), z = range (m)",
            "depth": "ground_truth/depth/*.npy: float32 range from camera centre along the pixel-centre ray, "
            "metres; inf = open water (I = B_inf, J = 0)",
            "images": "16-bit PNG, RGB order, value/65535 = linear radiance",
            "sfm_depth": "depth/*.png: sparse z-depth in millimetres at textured pixels (0 = unknown), "
            "like structure-from-motion points; nerfstudio's depth_file_path",
            "geometry": vars(geometry),
            "pose_convention": "nerfstudio/OpenGL camera-to-world (camera looks along -z, +y up)",
            "width": w,
            "height": h,
            "num_views": n_views,
            "seed": config.seed,
            "supersample": ss,
            "horizontal_fov_deg": HORIZONTAL_FOV_DEG,
            "holdout_every": HOLDOUT_EVERY,
            "open_water_fraction": n_open / float(n_views * w * h),
        }
        (tmp / "ground_truth" / "medium.json").write_text(json.dumps(med, indent=2) + "\n")

    CONSOLE.print(
        f"seathru-synth: wrote {n_views} views ({w}x{h}, preset={config.preset}, seed={config.seed}) "
        f"to {out} in {time.perf_counter() - start:.1f}s"
    )
    return out


def entrypoint() -> None:
    """Console script: exit status 1 with a one-line reason on bad options or a busy folder."""
    silence_upstream_warnings()
    config = tyro.cli(SynthConfig)
    try:
        generate(config)
    except (SynthError, OutputFolderError) as error:
        CONSOLE.print(f"[bold red]Error: seathru-synth: {error}")
        sys.exit(1)


if __name__ == "__main__":
    entrypoint()
