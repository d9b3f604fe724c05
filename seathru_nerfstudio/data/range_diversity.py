"""How much the capture tells about the attenuation: the range spread of the SfM points.

A surface point seen at range ``z`` shows ``J e^{-β_D z} + B∞ (1 - e^{-β_B z})``. Its unknown
colour ``J`` absorbs any common factor, so the attenuation ``β_D`` is determined only by how the
point's brightness changes between views *at different ranges*. A flat forward-facing rig keeps
those differences small (on the water demo a point's range varies by 5 cm between the views that
see it, 3% of its range), and a 25% error in ``β_D`` then costs the images almost nothing
(0eb30e8, 2026-11-25; docs/history.md). This module measures that spread from what every capture has:
the sparse SfM depths and the poses, before any training.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class RangeSpread:
    """Statistics of the SfM points' ranges over the views that see them (world units)."""

    num_points: int
    """SfM points inside at least two views' images."""
    mean_views: float
    """Views per point (the point's own included)."""
    mean_range: float
    """Mean over points of the point's mean range from the camera centres."""
    spread: float
    """Mean over points of the standard deviation of the point's range across its views."""

    @property
    def relative_spread(self) -> float:
        """``spread / mean_range``: the fraction by which a point's distance varies."""
        return self.spread / self.mean_range if self.mean_range > 0 else 0.0

    def summary(self) -> str:
        """One readable line for the training log."""
        return (
            f"SfM range spread: {self.num_points} points, each in {self.mean_views:.1f} views; a point's range varies by "
            f"{self.spread:.3g} (std, world units) around {self.mean_range:.3g}, {100 * self.relative_spread:.1f}%. "
            "The attenuation is set only by these differences: views at more varied distances determine it better."
        )


def back_project(
    depth: npt.NDArray[np.floating], c2w: npt.NDArray[np.float64], fx: float, fy: float, cx: float, cy: float, max_points: int
) -> npt.NDArray[np.float64]:
    """(P, 3) world points of a z-depth map's known pixels (an evenly strided subset beyond
    ``max_points``), for a nerfstudio/OpenGL camera-to-world ``c2w`` (3, 4); pixel centres at +0.5."""
    depth = np.asarray(depth, dtype=np.float64)
    v, u = np.nonzero(depth > 0)
    stride = max(1, -(-u.size // max_points))
    v, u = v[::stride], u[::stride]
    z = depth[v, u]
    camera = np.stack([(u + 0.5 - cx) / fx * z, -(v + 0.5 - cy) / fy * z, -z], axis=-1)
    return camera @ c2w[:, :3].T + c2w[:, 3]


def project(
    points: npt.NDArray[np.float64], c2w: npt.NDArray[np.float64], fx: float, fy: float, cx: float, cy: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """``(u, v, ahead)``: continuous pixel coordinates (centres at +0.5) and z-depth in front of
    the camera (<= 0: behind it, where ``u`` and ``v`` are meaningless) of world ``points``."""
    local = (points - c2w[:, 3]) @ c2w[:, :3]
    ahead = -local[:, 2]
    safe = np.where(ahead > 0, ahead, 1.0)
    return fx * local[:, 0] / safe + cx, -fy * local[:, 1] / safe + cy, ahead


def range_spread(
    z_depths: Sequence[npt.NDArray[np.floating]],
    camera_to_worlds: npt.NDArray[np.floating],
    fx: npt.NDArray[np.floating],
    fy: npt.NDArray[np.floating],
    cx: npt.NDArray[np.floating],
    cy: npt.NDArray[np.floating],
    max_points_per_view: int = 500,
) -> RangeSpread:
    """Back-project every known pixel of each sparse depth map and measure its range from every
    camera whose image it falls in (pinhole, no occlusion test: SfM points are on visible texture).

    Args:
        z_depths: per view, an (H, W) map of z-depth along the camera's viewing axis, 0 = unknown.
        camera_to_worlds: (N, 3, 4) nerfstudio/OpenGL camera-to-world (the camera looks along -z,
            +y up); pixel centres at +0.5.
        fx, fy, cx, cy: (N,) pinhole intrinsics in pixels.
        max_points_per_view: an evenly strided subset of each view's points beyond this many (the
            statistics are means, and a capture of hundreds of views would otherwise cost
            views² × points at every start).
    """
    if max_points_per_view < 1:
        raise ValueError(f"range_spread: max_points_per_view must be at least 1, got {max_points_per_view}")
    c2w = np.asarray(camera_to_worlds, dtype=np.float64)
    sizes = [np.asarray(d).shape for d in z_depths]
    per_point_ranges = []
    for i, depth in enumerate(z_depths):
        points = back_project(depth, c2w[i], fx[i], fy[i], cx[i], cy[i], max_points_per_view)
        if len(points) == 0:
            continue
        ranges = np.full((len(z_depths), len(points)), np.nan)
        for j, (height, width) in enumerate(sizes):
            pu, pv, ahead = project(points, c2w[j], fx[j], fy[j], cx[j], cy[j])
            inside = (ahead > 0) & (pu >= 0) & (pu < width) & (pv >= 0) & (pv < height)
            ranges[j, inside] = np.linalg.norm(points[inside] - c2w[j, :, 3], axis=-1)
        per_point_ranges.append(ranges)
    if not per_point_ranges:
        return RangeSpread(0, 0.0, 0.0, 0.0)
    ranges = np.concatenate(per_point_ranges, axis=1)
    views = np.sum(np.isfinite(ranges), axis=0)
    seen = views >= 2
    if not np.any(seen):
        return RangeSpread(0, 0.0, 0.0, 0.0)
    ranges = ranges[:, seen]
    return RangeSpread(
        num_points=int(seen.sum()),
        mean_views=float(views[seen].mean()),
        mean_range=float(np.nanmean(ranges, axis=0).mean()),
        spread=float(np.nanstd(ranges, axis=0).mean()),
    )
