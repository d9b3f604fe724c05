"""``seathru-trim-mesh``: a mesh from ``ns-export`` without the faces the trained model sees as open water.

nerfstudio's TSDF starts every voxel "inside" and meshes all of them, so the border between the
water that the views carved and the voxels no view sees becomes faces, some of them in the open
water; a Poisson surface closes around the point cloud and bulges past it (docs/export.md). Both
are nerfstudio's exporters, used as they are; this command removes those vertices afterwards.

A vertex is in the water when a view of the run's photos (training and held out) looks through it.
It projects into the view's image, and there:

* the ray meets no surface: the model's object opacity (``accumulation``), interpolated bilinearly
  between pixel centres at the vertex's projection, is at most 0.5 (the opacity nerfstudio's point
  cloud keeps a ray's point above). Interpolated, the silhouette lies where the opacity crosses 0.5
  between two pixel centres, not on the pixel's edge: a vertex on an object's outline stays;
* or the ray meets one beyond it: its distance from the camera centre is less than the model's
  ``depth`` there minus a margin. The depth is interpolated bilinearly too, over the opaque pixels
  only (weighted by opacity): on a slanted surface it changes across a pixel by more than the
  mesh's resolution. The margin is the mesh's own resolution (by
  default twice its median edge length): a vertex of a surface lies up to about an edge off the
  model's surface, and must stay.

A vertex that no view sees, behind the surfaces or outside every frustum, stays: nothing says it
is water.

Units: scene units (nerfstudio's frame, as ``ns-export`` writes meshes), ranges along unit rays.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
import numpy.typing as npt
import torch

from seathru_nerfstudio.data.io import atomic_file
from seathru_nerfstudio.data.sfm_observations import bilinear
from seathru_nerfstudio.export import OPACITY_THRESHOLD


def seen_through(
    points: npt.NDArray[np.floating],
    camera_to_world: npt.NDArray[np.floating],
    intrinsics: tuple[float, float, float, float],
    opacity: npt.NDArray[np.floating],
    depth: npt.NDArray[np.floating],
    margin: float,
) -> npt.NDArray[np.bool_]:
    """Which ``points`` ``(N, 3)`` one view looks through. ``camera_to_world``: ``(3, 4)``,
    nerfstudio's OpenGL camera (x right, y up, looking along -z); ``intrinsics``: ``fx, fy, cx, cy``
    in pixels; ``opacity``, ``depth``: ``(H, W)``, each pixel-centre ray's object opacity and the
    range (along the unit ray) at which it meets the object. A point is looked through when it
    projects inside the image and the bilinear opacity there is at most
    :data:`~seathru_nerfstudio.export.OPACITY_THRESHOLD`, or its distance is below
    ``depth - margin`` there (``margin`` in scene units), the depth interpolated bilinearly over the
    opaque pixels (weighted by ``opacity``)."""
    fx, fy, cx, cy = intrinsics
    rotation, centre = camera_to_world[:, :3], camera_to_world[:, 3]
    local = (points - centre) @ rotation
    forward = -local[:, 2]
    in_front = forward > 1e-9
    safe = np.where(in_front, forward, 1.0)
    u = cx + fx * local[:, 0] / safe
    v = cy - fy * local[:, 1] / safe
    col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    height, width = opacity.shape
    inside = in_front & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    looked_through = np.zeros(len(points), dtype=bool)
    distance = np.linalg.norm(points[inside] - centre, axis=-1)
    weight = bilinear(opacity, u[inside], v[inside])
    weighted_depth = np.where(opacity > 0, opacity * np.minimum(depth, 1e30), 0.0)  # no 0 * inf
    surface = bilinear(weighted_depth, u[inside], v[inside]) / np.maximum(weight, 1e-12)
    open_ray = weight <= OPACITY_THRESHOLD
    nearer = distance < surface - margin
    looked_through[inside] = open_ray | nearer
    return looked_through


def median_edge_length(mesh: Any) -> float:
    """The median length of an open3d triangle mesh's edges (scene units): its resolution."""
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    if len(triangles) == 0:
        return 0.0
    corners = vertices[triangles]  # (F, 3 corners, 3)
    edges = corners - np.roll(corners, 1, axis=1)
    return float(np.median(np.linalg.norm(edges, axis=-1)))


def open_water_vertices(pipeline, vertices: npt.NDArray[np.floating], margin: float) -> npt.NDArray[np.bool_]:
    """The vertices (scene units) that some view of ``pipeline``'s photos (training and held out)
    looks through, as its model renders them."""
    water = np.zeros(len(vertices), dtype=bool)
    for dataset in (pipeline.datamanager.train_dataset, pipeline.datamanager.eval_dataset):
        cameras = dataset.cameras.to(pipeline.device)
        for index in range(len(cameras)):
            camera = cameras[index : index + 1]
            with torch.no_grad():
                outputs = pipeline.model.get_outputs_for_camera(camera)
            opacity = outputs["accumulation"][..., 0].double().cpu().numpy()
            depth = outputs["depth"][..., 0].double().cpu().numpy()
            intrinsics = tuple(float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
            c2w = camera.camera_to_worlds.reshape(3, 4).double().cpu().numpy()
            water |= seen_through(vertices, c2w, intrinsics, opacity, depth, margin)  # type: ignore[arg-type]
    return water


@dataclass
class TrimMeshCommand:
    """Remove from a mesh written by ``ns-export`` (PLY with vertex colours) every vertex a view of the
    run's photos looks through, and the faces that use it."""

    load_config: Path
    """The run's ``config.yml``."""
    mesh: Path
    """The mesh to trim, e.g. ``exports/tsdf_mesh.ply`` or ``exports/poisson_mesh.ply``; it is not changed."""
    output: Optional[Path] = None
    """Where to write the trimmed mesh (default: beside it, ``<name>_trimmed.ply``)."""
    margin: Optional[float] = None
    """A vertex is water when nearer than its pixel's surface depth minus this (scene units; default: twice the mesh's median edge length)."""

    def main(self) -> int:
        for path, what in ((self.load_config, "give a run's config.yml"), (self.mesh, "give a mesh from ns-export")):
            if not path.is_file():
                print(f"seathru-trim-mesh: {path}: no such file ({what})", file=sys.stderr)
                return 2
        if self.mesh.suffix.lower() != ".ply":
            print(f"seathru-trim-mesh: {self.mesh}: not a .ply (textured meshes are not trimmed)", file=sys.stderr)
            return 2
        if self.margin is not None and not (math.isfinite(self.margin) and self.margin >= 0.0):
            print(f"seathru-trim-mesh: --margin must be a distance >= 0 in scene units (got {self.margin})", file=sys.stderr)
            return 2
        import open3d as o3d
        from nerfstudio.utils.eval_utils import eval_setup

        mesh = o3d.io.read_triangle_mesh(str(self.mesh))
        if len(mesh.vertices) == 0:
            print(f"seathru-trim-mesh: {self.mesh}: no vertices (not a mesh open3d can read)", file=sys.stderr)
            return 2
        _, pipeline, _, _ = eval_setup(self.load_config, test_mode="test")
        margin = self.margin if self.margin is not None else 2.0 * median_edge_length(mesh)
        water = open_water_vertices(pipeline, np.asarray(mesh.vertices), margin)
        mesh.remove_vertices_by_mask(water.tolist())
        output = self.output or self.mesh.with_name(f"{self.mesh.stem}_trimmed.ply")
        try:
            with atomic_file(output, suffix=".ply") as temporary:
                if not o3d.io.write_triangle_mesh(str(temporary), mesh):
                    raise OSError("open3d could not write it")
        except OSError as error:
            print(f"seathru-trim-mesh: {output}: {error}", file=sys.stderr)
            return 1
        print(f"seathru-trim-mesh: removed {int(water.sum())} of {len(water)} vertices in open water; wrote {output}")
        return 0


def entrypoint() -> None:
    """``seathru-trim-mesh``."""
    import tyro

    from seathru_nerfstudio.quiet import silence_upstream_warnings

    silence_upstream_warnings()
    raise SystemExit(tyro.cli(TrimMeshCommand).main())


if __name__ == "__main__":
    entrypoint()
