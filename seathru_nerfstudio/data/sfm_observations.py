"""What the SfM points look like from every view that sees them: ranges and colours.

A surface point at range ``z`` from a camera shows ``J e^{-β_D z} + B∞ (1 - e^{-β_B z})``
(the paper's Eq. 5 for one opaque surface). Seen from several views at different ranges, its
colour changes only through the medium, so a table of (range, colour) per point and view
determines the densities once the veiling light is known (:mod:`seathru_nerfstudio.medium_fit`).

Each sparse depth pixel is first moved to the flattest pixel near it in its own view (below), then
back-projected and projected into every view. A projection counts as
an observation only where that view's own sparse depth map holds a point within
``window`` pixels at the same z-depth (to ``depth_tolerance``): the surface is visible there,
not hidden behind another. Colours are sampled bilinearly from the linear images.

Why move the points: SfM finds its points where the image is most textured, and there a colour
looked up between pixels, with a footprint that differs from view to view, changes with the view
by as much as the medium does over the few per cent by which the point's range changes. The fit
reads that as attenuation. Offline, with the true veiling light, on the three demos' SfM tables
(5140fdb, 2026-11-27; docs/history.md), the fitted β_D was off by +3, +4, +9% (water), +1, −8, −1%
(turbid) and −2, +1, +3% (fog) at the SfM pixels; moved to the flattest pixel within 2 px at the
same z-depth (the surface taken as locally facing the camera), by +2, +1, 0%, +1, −4, +1% and
−1, +1, 0%. Points sampled at low-texture pixels with their true depth fit within 1–3%.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import numpy.typing as npt

from seathru_nerfstudio.data.range_diversity import back_project, project


@dataclass(frozen=True)
class SfmObservations:
    """Per SfM point ``p`` and view ``v``: the range (world units) and the linear colour seen."""

    ranges: npt.NDArray[np.float64]
    """(P, V) distance from view ``v``'s camera centre to point ``p``; NaN where not observed."""
    colours: npt.NDArray[np.float64]
    """(P, V, 3) linear RGB at the point's projection in view ``v``; NaN where not observed."""

    @property
    def num_points(self) -> int:
        return int(self.ranges.shape[0])

    @property
    def num_observations(self) -> int:
        return int(np.isfinite(self.ranges).sum())


def bilinear(image: npt.NDArray[np.floating], u: npt.NDArray[np.float64], v: npt.NDArray[np.float64]) -> npt.NDArray[np.floating]:
    """``image`` ``(H, W, ...)`` interpolated bilinearly at continuous pixel coordinates ``(u, v)``
    (pixel ``(r, c)``'s centre at ``(c + 0.5, r + 0.5)``), clamped to the outermost pixel centres."""
    height, width = image.shape[:2]
    x, y = np.clip(u - 0.5, 0.0, width - 1.0), np.clip(v - 0.5, 0.0, height - 1.0)
    x0 = np.clip(np.floor(x).astype(int), 0, max(width - 2, 0))
    y0 = np.clip(np.floor(y).astype(int), 0, max(height - 2, 0))
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    trailing = (1,) * (image.ndim - 2)
    ax, ay = (x - x0).reshape(-1, *trailing), (y - y0).reshape(-1, *trailing)
    return (
        image[y0, x0] * (1 - ax) * (1 - ay)
        + image[y0, x1] * ax * (1 - ay)
        + image[y1, x0] * (1 - ax) * ay
        + image[y1, x1] * ax * ay
    )


def at_flattest_pixels(
    z_depth: npt.NDArray[np.floating], image: npt.NDArray[np.floating], within: int
) -> npt.NDArray[np.float64]:
    """The sparse z-depth map with each known pixel moved, at the same z-depth, to the pixel of
    least image gradient (``|∇|`` of the mean over RGB, central differences) within ``within``
    pixels (a square window), where that pixel is strictly flatter; ties go to the nearest. Two
    points moved onto one pixel leave one."""
    depth = np.asarray(z_depth, dtype=np.float64)
    rows, cols = np.nonzero(depth > 0)
    if within <= 0 or rows.size == 0:
        return depth.copy()
    height, width = depth.shape
    grey = np.asarray(image, dtype=np.float64)[..., :3].mean(axis=-1)
    gradient_y, gradient_x = np.gradient(grey)
    texture = np.hypot(gradient_x, gradient_y)
    best_rows, best_cols, best_texture = rows.copy(), cols.copy(), texture[rows, cols]
    offsets = sorted(
        ((dy, dx) for dy in range(-within, within + 1) for dx in range(-within, within + 1)), key=lambda o: o[0] ** 2 + o[1] ** 2
    )
    for dy, dx in offsets:
        r, c = rows + dy, cols + dx
        inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
        candidate = np.where(inside, texture[np.clip(r, 0, height - 1), np.clip(c, 0, width - 1)], np.inf)
        flatter = candidate < best_texture
        best_rows[flatter], best_cols[flatter], best_texture[flatter] = r[flatter], c[flatter], candidate[flatter]
    moved = np.zeros_like(depth)
    moved[best_rows, best_cols] = depth[rows, cols]
    return moved


def sfm_observations(
    z_depths: Sequence[npt.NDArray[np.floating]],
    images: Sequence[npt.NDArray[np.floating]],
    camera_to_worlds: npt.NDArray[np.floating],
    fx: npt.NDArray[np.floating],
    fy: npt.NDArray[np.floating],
    cx: npt.NDArray[np.floating],
    cy: npt.NDArray[np.floating],
    max_points_per_view: int = 500,
    window: int = 2,
    depth_tolerance: float = 0.03,
    max_points: int = 20000,
    flattest_within: int = 2,
) -> SfmObservations:
    """The observation table of the sparse depth maps' points.

    Args:
        z_depths: per view, an (H, W) z-depth map (world units, along the viewing axis), 0 = unknown.
        images: per view, the (H, W, 3) linear image the depths belong to.
        camera_to_worlds: (N, 3, 4) nerfstudio/OpenGL camera-to-world (looks along -z, +y up), world units.
        fx, fy, cx, cy: (N,) pinhole intrinsics in pixels.
        max_points_per_view: an evenly strided subset of each view's points beyond this many.
        window: a projection is visible if the view's sparse map has a point within this many pixels...
        depth_tolerance: ...whose z-depth matches the projection's to this fraction.
        max_points: fewer points per view where the views are many: the table is dense
            (points × views), 20000 points × 200 views is 130 MB.
        flattest_within: each point first moves to the flattest pixel within this many pixels
            of its own view (:func:`at_flattest_pixels`; 2, as ``window``: what the visibility test
            already treats as the same surface); 0: the SfM pixels as they are.

    ``images`` is read one view at a time (``images[j]``), so it may load lazily; with
    ``flattest_within`` each is read twice.
    """
    if max_points_per_view < 1 or max_points < 1 or window < 0 or not depth_tolerance > 0 or flattest_within < 0:
        raise ValueError(
            "sfm_observations: need max_points_per_view >= 1, max_points >= 1, window >= 0, depth_tolerance > 0, "
            f"flattest_within >= 0; got {max_points_per_view}, {max_points}, {window}, {depth_tolerance}, {flattest_within}"
        )
    max_points_per_view = max(1, min(max_points_per_view, max_points // max(1, len(z_depths))))
    if len(images) != len(z_depths):
        raise ValueError(f"sfm_observations: {len(z_depths)} depth maps but {len(images)} images")
    c2w = np.asarray(camera_to_worlds, dtype=np.float64)
    depths = [np.asarray(d, dtype=np.float64) for d in z_depths]
    if flattest_within > 0:
        depths = [at_flattest_pixels(depth, images[i], flattest_within) for i, depth in enumerate(depths)]
    points = [back_project(depth, c2w[i], fx[i], fy[i], cx[i], cy[i], max_points_per_view) for i, depth in enumerate(depths)]
    points = [p for p in points if len(p)]
    if not points:
        return SfmObservations(np.zeros((0, len(depths))), np.zeros((0, len(depths), 3)))
    xyz = np.concatenate(points)
    ranges = np.full((len(xyz), len(depths)), np.nan)
    colours = np.full((len(xyz), len(depths), 3), np.nan)
    for j, depth in enumerate(depths):
        height, width = depth.shape
        pu, pv, ahead = project(xyz, c2w[j], fx[j], fy[j], cx[j], cy[j])
        inside = (ahead > 0) & (pu >= 0.5) & (pu < width - 1.5) & (pv >= 0.5) & (pv < height - 1.5)
        rows, cols = np.floor(pv[inside]).astype(int), np.floor(pu[inside]).astype(int)
        visible = np.zeros(rows.size, dtype=bool)
        for dy in range(-window, window + 1):
            for dx in range(-window, window + 1):
                known = depth[np.clip(rows + dy, 0, height - 1), np.clip(cols + dx, 0, width - 1)]
                visible |= (known > 0) & (np.abs(known - ahead[inside]) < depth_tolerance * ahead[inside])
        seen = np.nonzero(inside)[0][visible]
        image = np.asarray(images[j], dtype=np.float64)
        ranges[seen, j] = np.linalg.norm(xyz[seen] - c2w[j, :, 3], axis=-1)
        colours[seen, j] = bilinear(image, pu[seen], pv[seen])
    multi = np.isfinite(ranges).sum(axis=1) >= 2  # one view alone says nothing about the medium
    return SfmObservations(ranges=ranges[multi], colours=colours[multi])
