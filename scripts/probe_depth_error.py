"""Where is a trained run's depth wrong? (About a minute of CPU per run on 2 cores; needs a run saved
with ``seathru-bench run --save-model`` or ``ns-train``, and the scene's ground truth.)

Renders the run's held-out views and keeps the object pixels (``ground_truth/depth`` finite: the
true range in world units, metres on ``seathru-pathtrace`` scenes). The benchmark's mean depth
error is the mean of ``|depth − range| / range`` over them. Printed, by fifth of the true range:

* the true direct transmittance ``e^{−β z}`` at the band's middle range, with ``β`` the truth's
  smallest attenuation (``ground_truth/medium.json``): how much of a surface's own light reaches
  the camera in the clearest channel;
* the band's mean and median abs-rel and its share of the error sum;
* the median ``log(depth / range)`` (< 0: surfaces placed too near);
* the share of pixels more than 25% off, and how many of those are too near;
* the mean object opacity.

Then the mean abs-rel over the pixels whose transmittance is above 5% and over the rest, within the
SfM far bound and beyond it (where no SfM depth says where a surface is), and where
the surfaces placed too near end up against the median depth the run gives the open water (where
it fills the open water with a wall, ``scripts/probe_open_water.py``). It says whether the mean
error comes from surfaces the water hides (where the images barely fix a range) or from ones it
shows, and whether a wall in the open water stands in front of them.

Last, within and beyond the far bound, the median log ratio by the cosine between the ray and the true
surface normal (from the range map's gradients, :func:`incidence_cosines`): whether a surface placed
too near is one the ray grazes (a blurred surface meets a grazing ray early) or one past the SfM's reach.

For a run with a medium, last of all, within and beyond the bound: the observed colour beside the
backscatter the run's medium gives at the true range, ``c_med (1 − e^{−σ_bs z / G})`` per ray as it renders
it (``G`` the veil's rise looking up, :func:`~seathru_nerfstudio.rendering.depth_lit_backscatter_density`), and the
scene's best fit gives there, and the share of pixels whose colour is darker than that in some channel:
there the run could put the surface at its true range only with ``J < 0``, so it moves it nearer. A
veil brighter than the surfaces' makes far surfaces come near (coastal 7, docs/history.md, 2026-12-07 (after dffa48e)).

    .venv/bin/python scripts/probe_depth_error.py RUN/config.yml outputs/pathtraced/turbid_s3
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Tuple

import numpy as np

NUM_BANDS = 5
FAR_OFF = 0.25
"""An abs-rel above this counts as a pixel placed wrong."""
INCIDENCE_BINS = ((0.0, 0.15), (0.15, 0.3), (0.3, 0.5), (0.5, 1.01))
"""Bins of ``|cos|`` between the ray and the surface normal (below 0.15: the ray grazes, under 9°)."""
MIN_BIN_PIXELS = 20
"""A bin with fewer pixels is not printed."""
VISIBLE_TRANSMITTANCE = 0.05
"""A surface counts as shown by the water where at least this share of its light reaches the camera."""


def incidence_cosines(camera, true_range: np.ndarray) -> np.ndarray:
    """``|cos|`` of the angle between each pixel's ray and the true surface normal, ``(H, W)``: the
    surface points ``range × direction`` (camera at the origin; the range map in world units, the
    directions unit vectors), the normal the cross product of their image gradients; nan on open water
    and where a neighbour is open water."""
    directions = camera.generate_rays(camera_indices=0).directions.numpy().astype(np.float64)
    points = directions * np.where(np.isfinite(true_range), true_range, np.nan)[..., None]
    normals = np.cross(np.gradient(points, axis=1), np.gradient(points, axis=0))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True) + 1e-12
    return np.abs(np.sum(normals * directions, axis=-1))


def object_depths(config: Path, scene: Path) -> Tuple[dict, float]:
    """Per object pixel of every held-out view: ``range`` (true, world units), ``depth`` (the run's
    median depth, world units) and ``accumulation``; ``open_depth``: the run's depth on the open water;
    and the SfM far bound in world units (nan without one)."""
    from held_out_views import held_out_renders, load_run

    pipeline, scale = load_run(config)
    far_plane = pipeline.datamanager.train_dataparser_outputs.metadata.get("far_plane")
    far_bound = float(far_plane) / scale if far_plane is not None else float("nan")
    from seathru_nerfstudio.data.linear_images import read_linear_image
    from seathru_nerfstudio.medium_field import SceneMedium
    from seathru_nerfstudio.rendering import depth_lit_backscatter_density

    columns = {k: [] for k in ("range", "depth", "accumulation", "open_depth", "cosine", "observed", "run_backscatter")}
    for _, name, camera, true_range, outputs in held_out_renders(pipeline, scene):
        objects = np.isfinite(true_range) & (true_range > 0)
        if "medium_rgb" in outputs:  # the run's backscatter at the true range, per channel, as it renders it
            density = outputs["medium_backscatter"]
            medium = pipeline.model.medium_field
            if isinstance(medium, SceneMedium):  # a veil raised looking up keeps the level rate in front of a surface
                directions = camera.generate_rays(camera_indices=0).directions.to(density.device)
                density = depth_lit_backscatter_density(density, medium.rendered_veil_gain(directions))
            density = density.numpy()[objects].astype(np.float64) * scale
            veil = outputs["medium_rgb"].numpy()[objects].astype(np.float64)
            columns["run_backscatter"].append(veil * -np.expm1(-density * true_range[objects, None]))
            columns["observed"].append(read_linear_image(scene / "images" / f"{name}.png")[..., :3][objects].astype(np.float64))
        columns["cosine"].append(incidence_cosines(camera, true_range)[objects])
        depth = outputs["depth"][..., 0].numpy() / scale
        columns["range"].append(true_range[objects])
        columns["depth"].append(depth[objects])
        columns["accumulation"].append(outputs["accumulation"][..., 0].numpy()[objects])
        columns["open_depth"].append(depth[~np.isfinite(true_range)])
    return {key: np.concatenate(parts) for key, parts in columns.items() if parts}, far_bound


def backscatter_at_true_range(samples: dict, scene: Path, beyond: np.ndarray, log_ratio: np.ndarray) -> None:
    """Print, within and beyond the far bound, the median observed colour, the run's and the best fit's
    backscatter at the true range, and the share of pixels darker than each in some channel."""
    truth = json.loads((scene / "ground_truth" / "medium.json").read_text())
    best_fit = np.asarray(truth["B_inf"]) * -np.expm1(-np.asarray(truth["beta_B"]) * samples["range"][:, None])
    observed, run = samples["observed"], samples["run_backscatter"]
    for label, mask in (("within the bound", ~beyond), ("beyond it", beyond)):
        if not mask.any():
            continue
        darker = (observed[mask] < run[mask]).any(axis=1)
        print(
            f"{label}: observed colour median {np.round(np.median(observed[mask], axis=0), 4)}, backscatter at the true "
            f"range: the run's {np.round(np.median(run[mask], axis=0), 4)}, the best fit's {np.round(np.median(best_fit[mask], axis=0), 4)}; "
            f"darker than the run's in some channel (J < 0 at the true range) {darker.mean():.0%} (log ratio "
            f"{np.median(log_ratio[mask][darker]) if darker.any() else float('nan'):+.3f}), than the best fit's "
            f"{(observed[mask] < best_fit[mask]).any(axis=1).mean():.0%}"
        )


def main(config: Path, scene: Path) -> None:
    samples, far_bound = object_depths(config, scene)
    true_range, depth = samples["range"], samples["depth"]
    if true_range.size == 0:
        sys.exit(f"{scene}: the held-out views show no object (ground_truth/depth is inf everywhere)")
    beta = min(json.loads((scene / "ground_truth" / "medium.json").read_text())["beta_D"])
    rel = np.abs(depth - true_range) / true_range
    log_ratio = np.log(np.maximum(depth, 1e-6) / true_range)
    print(f"{true_range.size} object pixels: abs-rel mean {rel.mean():.3f}, median {np.median(rel):.3f} (clearest β_D {beta} /m)")
    edges = np.quantile(true_range, np.linspace(0.0, 1.0, NUM_BANDS + 1))
    for low, high in zip(edges[:-1], edges[1:]):
        band = (true_range >= low) & (true_range <= high)
        off = rel[band] > FAR_OFF
        print(
            f"range {low:5.2f}–{high:5.2f}: transmittance {np.exp(-beta * 0.5 * (low + high)):.3f}, abs-rel mean "
            f"{rel[band].mean():.3f} median {np.median(rel[band]):.3f} ({rel[band].sum() / rel.sum():.0%} of the sum), "
            f"log ratio {np.median(log_ratio[band]):+.3f}, off by >{FAR_OFF:.0%}: {off.mean():.0%} "
            f"({np.mean(log_ratio[band][off] < 0) if off.any() else 0.0:.0%} too near), opacity {samples['accumulation'][band].mean():.3f}"
        )
    shown = np.exp(-beta * true_range) >= VISIBLE_TRANSMITTANCE
    for label, mask in (("shown", shown), ("hidden", ~shown)):
        if mask.any():
            print(f"transmittance {'≥' if label == 'shown' else '<'} {VISIBLE_TRANSMITTANCE}: {mask.mean():.0%} of the pixels, abs-rel mean {rel[mask].mean():.3f}")
    if np.isfinite(far_bound):
        beyond = true_range > far_bound
        for label, mask in ((f"within the SfM far bound ({far_bound:.2f})", ~beyond), ("beyond it", beyond)):
            if mask.any():
                print(
                    f"{label}: {mask.mean():.1%} of the pixels, {rel[mask].sum() / rel.sum():.0%} of the sum, abs-rel mean "
                    f"{rel[mask].mean():.3f}, log ratio {np.median(log_ratio[mask]):+.3f}, rendered depth median {np.median(depth[mask]):.2f}"
                )
        cosine = samples["cosine"]
        for label, mask in (("within the bound", ~beyond), ("beyond it", beyond)):
            bins = [f"{low:.2f}–{high:.2f}: {np.median(log_ratio[band]):+.3f} ({band.sum()})" for low, high in INCIDENCE_BINS
                    if (band := mask & (cosine >= low) & (cosine < high)).sum() >= MIN_BIN_PIXELS]  # fmt: skip
            print(f"{label}, median log ratio by |cos| of the ray against the surface normal (pixels): {'; '.join(bins) or '–'}")
        if "run_backscatter" in samples:
            backscatter_at_true_range(samples, scene, beyond, log_ratio)
    too_near = (rel > FAR_OFF) & (log_ratio < 0)
    if too_near.any():
        open_depth = samples["open_depth"]
        print(
            f"placed >{FAR_OFF:.0%} too near: {too_near.mean():.0%} of the pixels, {rel[too_near].sum() / rel.sum():.0%} of the sum; "
            f"true range median {np.median(true_range[too_near]):.2f}, rendered {np.median(depth[too_near]):.2f}; "
            f"the open water's depth quartiles {', '.join(f'{v:.2f}' for v in np.quantile(open_depth, [0.25, 0.5, 0.75])) if open_depth.size else '–'}"
        )


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: probe_depth_error.py RUN/config.yml SCENE_FOLDER")
    main(Path(sys.argv[1]), Path(sys.argv[2]))
