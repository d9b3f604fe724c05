"""``seathru-pathtrace``: render a physically path-traced multi-view scene (Mitsuba 3) in water,
fog or clear air, in ``seathru-synth``'s dataset layout, with poses from our own SfM.

Steps: draw the layout from the seed; render every view (in-medium image, J, medium-free,
range, z-depth, object ids); fit the best SeaThru medium to the training views
(:mod:`~seathru_nerfstudio.data.pathtrace.truth`); run ``seathru-process-data`` on the
in-medium images once (it is repeatable to the bit, and retries its mapper with other initial
pairs and other descriptors itself: :func:`~seathru_nerfstudio.data.sfm.run_sfm`); align
the recovered poses to the true ones (:mod:`~seathru_nerfstudio.data.pathtrace.align`);
write ``transforms.json`` with the SfM poses, the SfM sparse depths in metres and the
ground-truth fields, ``ground_truth/medium.json`` and ``scene.json``.

The folder is built in a hidden sibling and renamed into place. Running again with the same
options finds ``scene.json``'s option hash and reuses the folder.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional

import cv2  # before pycolmap (seathru_nerfstudio.data.sfm explains why)
import numpy as np
import tyro

from nerfstudio.utils.rich_utils import CONSOLE
from seathru_nerfstudio.data.ground_truth import FRAME_FIELDS, GT_CLEAN_FILENAMES, GT_DEPTH_FILENAMES
from seathru_nerfstudio.data.io import OutputFolderError, atomic_output_folder, write_png16, write_png16_gray
from seathru_nerfstudio.data.pathtrace.align import rotation_error_deg, umeyama
from seathru_nerfstudio.data.pathtrace.presets import HOLDOUT_EVERY, PRESETS, Preset
from seathru_nerfstudio.data.pathtrace.render import PathtraceError, Renderer
from seathru_nerfstudio.data.pathtrace.scene import make_layout
from seathru_nerfstudio.data.pathtrace.truth import fit_veil_and_backscatter
from seathru_nerfstudio.data.synthetic.cameras import HORIZONTAL_FOV_DEG
from seathru_nerfstudio.quiet import silence_upstream_warnings

GENERATOR_VERSION = 2
"""Bumped when the same options would render a different scene (part of the cache key)."""
REGISTRATION_VERSION = 6
"""Bumped when the same renders would register otherwise (part of the cache key, not of the
renders' key: a cached scene keeps its renders and is registered again, in seconds). 2: the
mapper's model chosen among two starts by the observations it explains (``data/sfm.py``); 3: pooled
SIFT descriptors matched again where SIFT registers under 80% of the views; 4: the mapper starts until
two of its starts hold 80% of the views; 5: without a known focal length the camera is mapped from two starts,
COLMAP's uncalibrated guess and 1.2 × the long side marked as a prior (``data/sfm.py``, ``camera_starts``); 6: and
from a third, 0.5 × the long side marked as a prior."""
DEFAULT_ROOT = Path("outputs/pathtraced")
SUN_OPTIONS = ("sun_elevation_deg", "sun_azimuth_deg")
"""Options that replace the preset's sun (None: the preset's own)."""
EXTRA_FIELDS = {"dry": "gt_dry_file_path", "z_depth": "gt_z_depth_file_path", "ids": "gt_ids_file_path"}
"""Frame fields beside nerfstudio's and the benchmark's: the medium-free render (16-bit PNG),
the z-depth (.npy float32, m) and the object ids (.npy int16, -1 = open water)."""


@dataclass
class PathtraceConfig:
    """Render a path-traced scene (Mitsuba 3) into a SeaThru-NeRF dataset folder."""

    preset: str = "coastal"
    """coastal (blue-green water, c = 0.30/0.17/0.12 /m), turbid (green water), fog (grey,
    0.12 /m) or clear (no medium, bright sky and sun)."""
    output_dir: Optional[Path] = None
    """Folder to write; default outputs/pathtraced/<preset>."""
    seed: int = 0
    """Layout, cameras and Monte Carlo samples; the same seed gives the same renders."""
    width: int = 240
    height: int = 160
    num_views: int = 24
    """Every 8th view (0, 8, 16, ...) is held out for val/test."""
    spp: Optional[int] = None
    """Samples per pixel (default: the preset's, 256; turbid 1024). The Monte Carlo noise is kept
    (no denoising); where it is above the texture (64 in water, 256 in turbid water) no image registers."""
    max_depth: int = 24
    """Longest light path (scattering events + bounces)."""
    poses: Literal["sfm", "truth"] = "sfm"
    """sfm: poses and sparse depths from seathru-process-data, aligned to the truth; truth: the
    true poses and SfM-like sparse depths drawn from the true range (a diagnostic only)."""
    sfm_camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "OPENCV"] = "SIMPLE_PINHOLE"
    """--poses sfm: the camera model SfM calibrates; SIMPLE_PINHOLE is the renderer's (one focal
    length, no distortion): PINHOLE's two focal lengths came out 10% apart on turbid water."""
    sfm_focal_prior: bool = False
    """--poses sfm: SfM starts from the renderer's focal length, as from a calibrated camera's (still refined);
    off: from 1.2 x the long side, as for images without EXIF (refined alike)."""
    sfm_points_per_view: int = 300
    """--poses truth: sparse depth points per view."""
    variant: Literal["auto", "llvm_ad_rgb", "scalar_rgb"] = "auto"
    """Mitsuba variant (auto: llvm_ad_rgb when a libLLVM >= 19 is installed)."""
    overwrite: bool = False
    """Replace a folder that holds a different scene."""
    sun_elevation_deg: Optional[float] = None
    """The sun's elevation, degrees, in (0, 90] (default: the preset's, 60); in water its direction under the surface (41.4 or more)."""
    sun_azimuth_deg: Optional[float] = None
    """The sun's azimuth, degrees from behind the rig towards its right (default: the preset's, 30)."""

    def preset_used(self) -> Preset:
        """The preset with the sun options that are given in place of its own."""
        given = {name: getattr(self, name) for name in SUN_OPTIONS if getattr(self, name) is not None}
        return dataclasses.replace(PRESETS[self.preset], **given)

    def samples_per_pixel(self) -> int:
        """``spp``, or the preset's where it is not given."""
        return self.spp if self.spp is not None else PRESETS[self.preset].spp

    def folder(self) -> Path:
        return Path(self.output_dir if self.output_dir is not None else DEFAULT_ROOT / self.preset).expanduser().absolute()

    def cache_key(self, renders_only: bool = False) -> str:
        """Hash of the options that determine the folder (``renders_only``: the renders alone,
        without the pose options, so a new pose run reuses them)."""
        skip = {"output_dir", "overwrite", "variant"} | ({"poses", "sfm_camera_model", "sfm_focal_prior", "sfm_points_per_view"} if renders_only else set())
        skip |= set() if self.sfm_focal_prior else {"sfm_focal_prior"}  # off: the key scenes had before it existed
        skip |= {name for name in SUN_OPTIONS if getattr(self, name) is None}  # a scene cached before they existed keeps its key
        options = {k: v for k, v in dataclasses.asdict(self).items() if k not in skip}
        options["spp"] = self.samples_per_pixel()  # the default and its value name the same renders
        options["generator_version"] = GENERATOR_VERSION
        if not renders_only:
            options["registration_version"] = REGISTRATION_VERSION
        return hashlib.sha256(json.dumps(options, sort_keys=True, default=str).encode()).hexdigest()[:16]


def validate(config: PathtraceConfig) -> None:
    if config.preset not in PRESETS:
        raise PathtraceError(f"unknown preset {config.preset!r}; choose from {', '.join(PRESETS)}")
    if config.width < 8 or config.height < 8:
        raise PathtraceError("--width and --height must be at least 8 pixels")
    if config.num_views < 3:
        raise PathtraceError("--num-views must be at least 3")
    if (config.spp is not None and config.spp < 1) or config.max_depth < 1:
        raise PathtraceError("--spp and --max-depth must be at least 1")
    if config.sun_elevation_deg is not None and not 0.0 < config.sun_elevation_deg <= 90.0:
        raise PathtraceError(f"--sun-elevation-deg must be in (0, 90] degrees, got {config.sun_elevation_deg}")
    if config.sun_azimuth_deg is not None and not math.isfinite(config.sun_azimuth_deg):
        raise PathtraceError(f"--sun-azimuth-deg must be a finite angle, got {config.sun_azimuth_deg}")


def _read_record(folder: Path) -> Optional[Dict[str, Any]]:
    try:
        return json.loads((folder / "scene.json").read_text())
    except (OSError, json.JSONDecodeError):
        return None


def generate(config: PathtraceConfig) -> Path:
    """Render (or find cached) the scene of ``config``; returns its folder.

    A folder whose ``scene.json`` has the same option hash is returned as it is; one with the
    same renders (only the pose options differ, or its SfM failed) keeps its renders and gets
    new poses. Raises :class:`PathtraceError` on bad options, and after writing the renders when
    structure from motion registers fewer than 3 images (``--poses truth`` then reuses them),
    and ``OutputFolderError`` for a folder holding something else (without ``--overwrite``)."""
    validate(config)
    out = config.folder()
    key, render_key = config.cache_key(), config.cache_key(renders_only=True)
    record = _read_record(out)
    if record is not None and record.get("options_hash") == key and (out / "transforms.json").is_file():
        CONSOLE.print(f"seathru-pathtrace: {out} already holds this scene (options hash {key}); reusing it")
        return out
    reuse = record is not None and record.get("render_hash") == render_key
    if record is not None and not reuse and not config.overwrite:
        raise OutputFolderError(f"{out} holds a scene rendered with other options; pass --overwrite or choose another --output-dir")
    preset = config.preset_used()
    start = time.perf_counter()
    layout = make_layout(config.seed, config.num_views, preset)
    names = [f"frame_{i:05d}.png" for i in range(config.num_views)]
    held = [i % HOLDOUT_EVERY == 0 for i in range(config.num_views)]
    failure: Optional[PathtraceError] = None
    with atomic_output_folder(out, overwrite=reuse or config.overwrite) as build:
        if reuse:
            CONSOLE.print(f"seathru-pathtrace: reusing the renders in {out} (render hash {render_key})")
            for folder in ("images", "ground_truth"):
                shutil.copytree(out / folder, build / folder)
            views = _read_views(build, names)
            seconds, fit, variant = record["seconds_per_view"], record["best_fit_medium"], record["mitsuba_variant"]
        else:
            renderer = Renderer(layout, preset, config.width, config.height, config.samples_per_pixel(), config.max_depth, config.variant)
            try:
                views, seconds = _render_all(renderer, layout, config, build, names)
                variant = renderer.mi.variant()
            finally:
                renderer.close()
            train = [v for v, h in zip(views, held) if not h]
            if preset.medium == "none":
                fit = {"beta_D": [0.0] * 3, "beta_B": [0.0] * 3, "B_inf": [0.0] * 3, "rmse": None, "num_pixels": 0, "open_water_mean": None}
            else:
                fit = fit_veil_and_backscatter([v["image"] for v in train], [v["clean"] for v in train], [v["range"] for v in train], preset.sigma_t)
        _write_medium(build, preset, fit, config)
        summary: Dict[str, Any] = {
            "options": {**dataclasses.asdict(config), "output_dir": str(out), "spp": config.samples_per_pixel()},
            "options_hash": key,
            "render_hash": render_key,
            "generator_version": GENERATOR_VERSION,
            "mitsuba_variant": variant,
            "preset": preset.to_json(),
            "seconds_per_view": seconds,
            "best_fit_medium": fit,
            "open_water_fraction": float(np.mean([np.mean(~np.isfinite(v["range"])) for v in views])),
            "clipped_fraction": {k: float(np.mean([np.mean(v[k] >= 1.0) for v in views])) for k in ("image", "clean", "dry")},
            "holdout_every": HOLDOUT_EVERY,
        }
        try:
            if config.poses == "sfm":
                frames, camera, registration = _sfm_frames(build, names, layout.poses, config.sfm_camera_model, _prior_focal(config))
            else:
                frames, camera, registration = _true_frames(build, names, layout.poses, views, config)
            _write_transforms(build, frames, camera, names, held)
        except PathtraceError as error:  # keep the renders; no transforms.json, no options_hash
            failure, registration = error, {"poses": config.poses, "failed": str(error)}
            summary["options_hash"] = None
        summary["registration"] = registration
        previous = (record or {}).get("registration") or {}
        if reuse and (previous.get("failed") or previous.get("previous_sfm")):
            registration["previous_sfm"] = previous.get("previous_sfm") or previous  # what SfM did on these renders
        summary["seconds_total"] = time.perf_counter() - start
        (build / "scene.json").write_text(json.dumps(summary, indent=2) + "\n")
    if failure is not None:
        raise PathtraceError(f"{failure} (the renders are kept in {out}; --poses truth reuses them)")
    reg = registration
    poses = f"{reg['registered']}/{reg['total']} registered" if config.poses == "sfm" else "TRUE poses (diagnostic)"
    CONSOLE.print(
        f"seathru-pathtrace: {config.preset}: {config.num_views} views {config.width}x{config.height} at {config.samples_per_pixel()} spp "
        f"({seconds['total']:.1f} s/view), {poses}, into {out} "
        f"in {time.perf_counter() - start:.0f} s"
    )
    return out


def _read_views(folder: Path, names: List[str]) -> List[Dict[str, np.ndarray]]:
    """The stored renders (as the fit and ``--poses truth`` use them) of a rendered folder."""
    from seathru_nerfstudio.data.linear_images import read_linear_image

    views = []
    for name in names:
        stem = Path(name).stem
        view = {k: read_linear_image(folder / sub / name)[..., :3] for k, sub in (("image", "images"), ("clean", "ground_truth/clean"), ("dry", "ground_truth/dry"))}
        view["range"] = np.load(folder / "ground_truth/depth" / f"{stem}.npy")
        views.append(view)
    return views


def _render_all(renderer: Renderer, layout, config: PathtraceConfig, build: Path, names: List[str]):
    """Render and write every view; returns the images kept for the fit (clipped as stored)
    and the mean seconds per view per render."""
    for folder in ("images", "ground_truth/clean", "ground_truth/dry", "ground_truth/depth", "ground_truth/z_depth", "ground_truth/ids"):
        (build / folder).mkdir(parents=True)
    views, times = [], []
    for i, c2w in enumerate(layout.poses):
        view = renderer.render(c2w, seed=config.seed * 100003 + i)
        stem = Path(names[i]).stem
        write_png16(build / "images" / names[i], view.image)
        write_png16(build / "ground_truth/clean" / names[i], view.clean)
        write_png16(build / "ground_truth/dry" / names[i], view.dry)
        np.save(build / "ground_truth/depth" / f"{stem}.npy", view.range)
        np.save(build / "ground_truth/z_depth" / f"{stem}.npy", view.z_depth)
        np.save(build / "ground_truth/ids" / f"{stem}.npy", view.ids)
        clip = lambda a: np.clip(a, 0.0, 1.0)  # noqa: E731  (what the files hold)
        views.append({"image": clip(view.image), "clean": clip(view.clean), "dry": clip(view.dry), "range": view.range, "z_depth": view.z_depth})
        times.append(view.seconds)
        CONSOLE.print(f"  view {i + 1}/{len(layout.poses)}: " + ", ".join(f"{k} {s:.1f} s" for k, s in view.seconds.items()))
    seconds = {k: float(np.mean([t.get(k, 0.0) for t in times])) for k in times[0]}
    seconds["total"] = float(sum(seconds.values()))
    return views, seconds


def _prior_focal(config: PathtraceConfig) -> Optional[float]:
    """The renderer's focal length in pixels (horizontal field of view ``HORIZONTAL_FOV_DEG``) where
    ``--sfm-focal-prior`` asks SfM to start from it, else None."""
    return config.width / (2.0 * math.tan(math.radians(HORIZONTAL_FOV_DEG) / 2.0)) if config.sfm_focal_prior else None


def _sfm_frames(build: Path, names: List[str], true_poses: np.ndarray, camera_model: str, focal_length_px: Optional[float] = None):
    """Poses and sparse depths from ``seathru-process-data`` on the in-medium images (one shared
    ``camera_model``, COLMAP name, self-calibrated from ``focal_length_px`` where given), aligned to the
    true camera centres by a similarity."""
    from seathru_nerfstudio.data.process import ProcessDataError, ProcessSeathruData, process
    from seathru_nerfstudio.data.sfm import SfmError

    work = build / "_sfm"
    try:
        report = process(ProcessSeathruData(data=build / "images", output_dir=work, white_balance="none", camera_model=camera_model, focal_length_px=focal_length_px))
    except (SfmError, ProcessDataError) as error:
        raise PathtraceError(f"structure from motion failed on {build / 'images'}: {error}") from error
    count = len(report.sfm.registered)
    if count < 3:
        raise PathtraceError(f"structure from motion registered {count} of {len(names)} images: cannot align poses")
    sfm = json.loads((work / "transforms.json").read_text())
    index = {name: i for i, name in enumerate(names)}
    sfm_frames = sorted(sfm["frames"], key=lambda f: index[Path(f["file_path"]).name])
    ids = [index[Path(f["file_path"]).name] for f in sfm_frames]
    poses = np.array([f["transform_matrix"] for f in sfm_frames], dtype=np.float64)
    sim = umeyama(poses[:, :3, 3], true_poses[ids, :3, 3])
    aligned = [sim.apply_pose(p) for p in poses]
    residual = np.linalg.norm(np.array([a[:3, 3] for a in aligned]) - true_poses[ids, :3, 3], axis=1)
    (build / "depth").mkdir()
    frames = {}
    for i, frame, pose in zip(ids, sfm_frames, aligned):
        sparse = cv2.imread(str(work / frame["depth_file_path"]), cv2.IMREAD_UNCHANGED).astype(np.float64) * sim.scale
        sparse[sparse > 65535] = 0  # beyond a uint16 millimetre PNG: unknown rather than wrapped
        write_png16_gray(build / "depth" / names[i], np.round(sparse).astype(np.uint16))
        frames[i] = {"transform_matrix": pose.tolist(), "depth_file_path": f"depth/{names[i]}"}
    camera = {k: sfm[k] for k in ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h") if k in sfm}
    shutil.rmtree(work)
    registration = {
        "poses": "sfm",
        "registered": len(ids),
        "total": len(names),
        "unregistered": [names[i] for i in range(len(names)) if i not in frames],
        "alignment_scale_m_per_unit": sim.scale,
        "alignment_residual_rms_m": float(np.sqrt(np.mean(residual**2))),
        "alignment_residual_max_m": float(residual.max()),
        "rotation_error_deg_median": float(np.median([rotation_error_deg(a, true_poses[i]) for a, i in zip(aligned, ids)])),
    }
    return frames, camera, registration


def _true_frames(build: Path, names: List[str], true_poses: np.ndarray, views, config: PathtraceConfig):
    """The true poses and intrinsics, with SfM-like sparse depths drawn from the true range."""
    from seathru_nerfstudio.data.synthetic.cameras import intrinsics
    from seathru_nerfstudio.data.synthetic.render import sfm_like_depth

    K = intrinsics(config.width, config.height)
    (build / "depth").mkdir()
    frames = {}
    for i, (name, pose, view) in enumerate(zip(names, true_poses, views)):
        sparse = sfm_like_depth(view["clean"], view["range"], K, config.sfm_points_per_view, seed=(config.seed, i))
        write_png16_gray(build / "depth" / name, sparse)
        frames[i] = {"transform_matrix": pose.tolist(), "depth_file_path": f"depth/{name}"}
    camera = {"camera_model": "PINHOLE", **K, "w": config.width, "h": config.height}
    return frames, camera, {"poses": "truth", "registered": len(names), "total": len(names), "unregistered": []}


def _write_transforms(build: Path, frames: Dict[int, Dict[str, Any]], camera: Dict[str, Any], names: List[str], held: List[bool]) -> None:
    out_frames = []
    for i in sorted(frames):
        stem = Path(names[i]).stem
        out_frames.append({
            "file_path": f"images/{names[i]}",
            **frames[i],
            FRAME_FIELDS[GT_CLEAN_FILENAMES]: f"ground_truth/clean/{names[i]}",
            FRAME_FIELDS[GT_DEPTH_FILENAMES]: f"ground_truth/depth/{stem}.npy",
            EXTRA_FIELDS["dry"]: f"ground_truth/dry/{names[i]}",
            EXTRA_FIELDS["z_depth"]: f"ground_truth/z_depth/{stem}.npy",
            EXTRA_FIELDS["ids"]: f"ground_truth/ids/{stem}.npy",
        })
    present = [f"images/{names[i]}" for i in sorted(frames)]
    held_names = [n for n, i in zip(present, sorted(frames)) if held[i]]
    transforms = {
        **camera,
        "frames": out_frames,
        "train_filenames": [n for n, i in zip(present, sorted(frames)) if not held[i]],
        "val_filenames": held_names,
        "test_filenames": held_names,
    }
    (build / "transforms.json").write_text(json.dumps(transforms, indent=2) + "\n")


def _write_medium(build: Path, preset, fit: Dict[str, Any], config: PathtraceConfig) -> None:
    medium = {
        "preset": preset.name,
        "beta_D": list(preset.sigma_t),
        "beta_B": fit["beta_B"],
        "B_inf": fit["B_inf"],
        "units": "1/m",
        "world_units": "m",
        "color_space": "linear",
        "physical": {"medium": preset.medium, "sigma_t": list(preset.sigma_t), "albedo": list(preset.albedo), "g": preset.g, "phase": "henyey-greenstein", "layer_top_m": preset.layer_top},
        "fit": {"rmse": fit["rmse"], "num_pixels": fit["num_pixels"], "open_water_mean": fit["open_water_mean"],
                "how": "beta_D = sigma_t; B_inf, beta_B: least squares of I = J exp(-beta_D z) + B_inf (1 - exp(-beta_B z)) over the training views' object pixels"},
        "image_formation": "path traced (Mitsuba 3 volpathmis); SeaThru's formula holds only approximately",
        "depth": "ground_truth/depth/*.npy: float32 range along the pixel-centre ray, metres; inf = open water / sky",
        "clean": "ground_truth/clean: J, the radiance leaving the surface lit as in the medium, not attenuated towards the camera; 0 on open water",
        "images": "16-bit PNG, RGB order, value/65535 = linear radiance",
        "seed": config.seed,
        "width": config.width,
        "height": config.height,
        "num_views": config.num_views,
        "holdout_every": HOLDOUT_EVERY,
    }
    (build / "ground_truth" / "medium.json").write_text(json.dumps(medium, indent=2) + "\n")


def entrypoint() -> None:
    """Console script: exit status 1 with a one-line reason on bad options or a busy folder."""
    silence_upstream_warnings()
    config = tyro.cli(PathtraceConfig)
    try:
        generate(config)
    except (PathtraceError, OutputFolderError) as error:
        CONSOLE.print(f"[bold red]Error: seathru-pathtrace: {error}")
        sys.exit(1)


if __name__ == "__main__":
    entrypoint()
