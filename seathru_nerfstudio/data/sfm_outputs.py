"""The files structure from motion leaves for nerfstudio and LLFF readers: ``sparse/0``, sparse depth
maps, ``transforms.json``, ``sparse_pc.ply`` and ``poses_bounds.npy`` (conventions in
:mod:`seathru_nerfstudio.data.sfm`)."""

from __future__ import annotations

from pathlib import Path

import cv2  # noqa: F401  (before pycolmap, always: see seathru_nerfstudio.data.sfm)
import numpy as np
import numpy.typing as npt
import pycolmap

from seathru_nerfstudio.data.sfm import SfmError, SfmResult


def llff_poses_bounds(reconstruction: pycolmap.Reconstruction) -> tuple[list[str], npt.NDArray[np.float64]]:
    """LLFF ``poses_bounds.npy`` rows (N×17) for the registered images, sorted by name.

    Same layout as LLFF's ``imgs2poses``; near/far are the 0.1% / 99.9% percentiles of the
    depths (along the optical axis, COLMAP units) of the 3D points each image observes.
    """
    images = sorted((reconstruction.images[i] for i in reconstruction.reg_image_ids()), key=lambda im: im.name)
    points = {pid: p for pid, p in reconstruction.points3D.items()}
    all_xyz = np.array([p.xyz for p in points.values()]).reshape(-1, 3)
    rows = []
    for image in images:
        c2w = image.cam_from_world().inverse().matrix()  # 3x4, OpenCV axes
        camera = reconstruction.cameras[image.camera_id]
        hwf = np.array([camera.height, camera.width, camera.params[0]], dtype=np.float64)
        llff = np.stack([c2w[:, 1], c2w[:, 0], -c2w[:, 2], c2w[:, 3], hwf], axis=1)
        seen = [p2d.point3D_id for p2d in image.points2D if p2d.has_point3D()]
        xyz = np.array([points[pid].xyz for pid in seen]).reshape(-1, 3) if seen else all_xyz
        depths = (xyz - c2w[:, 3]) @ c2w[:, 2]
        depths = depths[depths > 0]
        near, far = (np.percentile(depths, [0.1, 99.9]) if depths.size else (np.nan, np.nan))
        rows.append(np.concatenate([llff.ravel(), [near, far]]))
    return [im.name for im in images], np.array(rows, dtype=np.float64).reshape(-1, 17)


SPARSE_DEPTH_SCALE = 1000.0
"""``depth/*.png`` hold z-depth × this as uint16 (nerfstudio's default ``depth_unit_scale_factor``
is its inverse)."""
SPARSE_DEPTH_MAX = 65535 / SPARSE_DEPTH_SCALE
"""The largest z-depth (COLMAP units) a uint16 depth PNG can hold; nerfstudio's
``create_sfm_depth`` casts with ``astype(np.uint16)``, which wraps anything beyond it."""
GAUGE_DEPTH_QUANTILE = 0.99
GAUGE_DEPTH_TARGET = 0.5 * SPARSE_DEPTH_MAX
"""The gauge puts the 99th percentile of the observed points' z-depths here (COLMAP units):
2× headroom below :data:`SPARSE_DEPTH_MAX` for the farthest points, and 1/32767 resolution
at that depth."""


def observed_depths(reconstruction: pycolmap.Reconstruction) -> npt.NDArray[np.float64]:
    """Z-depth (COLMAP units, along each camera's optical axis) of every observation of a 3D point."""
    depths = []
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.images[image_id]
        world_to_camera = image.cam_from_world().matrix()
        xyz = np.array([reconstruction.points3D[p.point3D_id].xyz for p in image.points2D if p.has_point3D()])
        if xyz.size:
            depths.append(xyz.reshape(-1, 3) @ world_to_camera[2, :3] + world_to_camera[2, 3])
    return np.concatenate(depths) if depths else np.zeros(0)


def normalise_gauge(reconstruction: pycolmap.Reconstruction) -> float:
    """Rescale the reconstruction in place so its sparse depths fit a uint16 depth PNG.

    The mapper's scale is arbitrary (set by its first image pair), and its points can sit
    past :data:`SPARSE_DEPTH_MAX`, where the depth PNGs would wrap around silently. A
    similarity changes nothing downstream: nerfstudio rescales the poses, and the depths
    move with them. Returns the factor applied (new units per old unit).
    """
    depths = observed_depths(reconstruction)
    depths = depths[depths > 0]
    if depths.size == 0:
        return 1.0
    factor = GAUGE_DEPTH_TARGET / float(np.quantile(depths, GAUGE_DEPTH_QUANTILE))
    reconstruction.transform(pycolmap.Sim3d(factor, pycolmap.Rotation3d(), np.zeros(3)))
    return factor


def write_outputs(result: SfmResult, output_dir: Path) -> None:
    """Write ``sparse/0`` (COLMAP binaries), ``depth/`` (the SfM points as sparse depth maps, via
    nerfstudio's ``create_sfm_depth``: 16-bit, COLMAP units x 1000, 0 = no point; the gauge is
    first rescaled by :func:`normalise_gauge` so they fit),
    ``transforms.json`` + ``sparse_pc.ply`` (via nerfstudio's ``colmap_to_json``, with each
    frame's ``depth_file_path``) and ``poses_bounds.npy`` into ``output_dir``.

    The sparse depths anchor the object field where SfM saw structure (``--pipeline.model.
    depth-loss-mult``): in water the image alone cannot tell a near dark surface from a far
    bright one.
    """
    # both pull in torch: only when needed
    from nerfstudio.process_data.colmap_utils import colmap_to_json, create_sfm_depth

    normalise_gauge(result.reconstruction)
    sparse = output_dir / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    result.reconstruction.write(sparse)
    depth_dir = output_dir / "depth"
    depth_dir.mkdir(exist_ok=True)
    depth_paths = create_sfm_depth(
        recon_dir=sparse,
        output_dir=depth_dir,
        verbose=False,
        depth_scale_to_integer_factor=SPARSE_DEPTH_SCALE,
        max_depth=SPARSE_DEPTH_MAX,  # drop, rather than wrap, the few points beyond the PNG's range
    )
    num_frames = colmap_to_json(recon_dir=sparse, output_dir=output_dir, image_id_to_depth_path=depth_paths)
    if num_frames != len(result.registered):
        raise SfmError(f"transforms.json has {num_frames} frames, expected {len(result.registered)}")
    _, rows = llff_poses_bounds(result.reconstruction)
    np.save(output_dir / "poses_bounds.npy", rows)
