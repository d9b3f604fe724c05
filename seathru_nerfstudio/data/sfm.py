"""Camera poses with pycolmap (no COLMAP binary), and the files nerfstudio / LLFF expect.

Conventions
-----------
* SIFT runs on a *display-transformed* 8-bit copy of each linear image (normalised, gamma
  1/2.2): linear underwater frames are dark and flat, and SIFT's contrast threshold would
  find few features in them. The copies carry the same file names as the linear images,
  so COLMAP's image names are the dataset's image names.
* COLMAP world units are arbitrary up to the written files: the mapper's scale is rescaled
  (:func:`normalise_gauge`) so the 99th percentile of the points' z-depths is 32.77 units,
  which the uint16 depth PNGs hold without wrapping. Camera frames are OpenCV (x right, y down, z forward), ``cam_from_world`` maps world to camera.
* ``transforms.json`` is written by nerfstudio's own ``colmap_to_json`` (OpenGL camera
  axes, z-up world, like ``ns-process-data``). ``poses_bounds.npy`` follows LLFF's
  ``imgs2poses``: one row per registered image sorted by name, a 3×5 matrix
  ``[down, right, backwards, centre, (h, w, f)]`` flattened, then near and far, the 0.1% /
  99.9% depth percentiles of the sparse points the image sees, in COLMAP units.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal

import cv2  # before pycolmap, always: see the note below
import numpy as np
import numpy.typing as npt
import pycolmap

from nerfstudio.utils.rich_utils import CONSOLE, get_progress, status

# Import order matters: pycolmap's extension exports its own zlib symbols. If it is loaded
# before OpenCV, OpenCV's libpng binds deflate* to it and cv2.imwrite(".png") aborts the
# process ("free(): invalid pointer"). Importing cv2 first binds OpenCV to the system zlib.

MatchingMethod = Literal["auto", "exhaustive", "sequential"]
EXHAUSTIVE_MAX_IMAGES = 50
"""``auto`` matching pairs every image with every other up to this many images (quadratic
cost), then switches to sequential matching (each image against its next neighbours)."""
DISPLAY_GAMMA = 2.2
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


class SfmError(RuntimeError):
    """Structure from motion could not produce a usable reconstruction."""


def display_transform(image: npt.NDArray[np.floating], percentile: float = 99.5) -> npt.NDArray[np.uint8]:
    """Linear RGB -> 8-bit display RGB for feature detection only (never for training).

    Divides by the image's own ``percentile`` value (over all channels), clips, and applies
    gamma ``1 / 2.2``; this lifts the shadows where underwater texture lives.
    """
    step = max(1, max(image.shape[:2]) // 1024)  # a strided sample is plenty for one percentile
    white = float(np.percentile(image[::step, ::step], percentile))
    normalised = np.clip(image / max(white, 1e-6), 0.0, 1.0)
    return np.round(normalised ** (1.0 / DISPLAY_GAMMA) * 255.0).astype(np.uint8)


def write_display_copy(path: Path, image: npt.NDArray[np.floating]) -> None:
    """Write :func:`display_transform` of a linear RGB image as an 8-bit PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), display_transform(image)[..., ::-1]):
        raise OSError(f"{path}: could not write image")


@dataclass
class SfmResult:
    """The largest reconstruction and which images it did / did not register."""

    reconstruction: pycolmap.Reconstruction
    registered: list[str]
    unregistered: list[str]

    @property
    def registration_rate(self) -> float:
        return len(self.registered) / max(1, len(self.registered) + len(self.unregistered))


@contextlib.contextmanager
def _colmap_logging(verbose: bool) -> Iterator[None]:
    """Silence COLMAP's INFO logging unless ``verbose``."""
    previous = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def run_sfm(
    image_dir: Path,
    work_dir: Path,
    camera_model: str = "OPENCV",
    matching: MatchingMethod = "auto",
    verbose: bool = False,
) -> SfmResult:
    """SIFT extraction, matching and incremental mapping on every image in ``image_dir``.

    One camera (``camera_model``, COLMAP name) is shared by all images; its focal length
    starts at 1.2 × the long side (no EXIF in the display copies) and is refined by bundle
    adjustment. ``work_dir`` receives ``database.db`` and the mapper's models. Returns the
    model with the most registered images; images outside it are ``unregistered``.
    Raises :class:`SfmError` when no model could be built.
    """
    names = sorted(p.name for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(names) < 2:
        raise SfmError(f"structure from motion needs at least 2 images, {image_dir} has {len(names)}")
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    if matching == "auto":
        matching = "exhaustive" if len(names) <= EXHAUSTIVE_MAX_IMAGES else "sequential"

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = 3200
    matching_options = pycolmap.FeatureMatchingOptions()
    mapper = pycolmap.IncrementalPipelineOptions()
    mapper.min_model_size = 3  # keep small models: we report a partial registration, not nothing
    mapper.random_seed = 0
    mapper.mapper.random_seed = 0
    mapper.triangulation.random_seed = 0

    with _colmap_logging(verbose):
        with status(f"[bold yellow]Extracting SIFT features from {len(names)} images...", verbose=verbose):
            pycolmap.extract_features(
                database,
                image_dir,
                image_names=names,
                camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
            )
        with status(f"[bold yellow]Matching features ({matching})...", verbose=verbose):
            if matching == "exhaustive":
                pycolmap.match_exhaustive(database, matching_options=matching_options, device=pycolmap.Device.cpu)
            else:
                pycolmap.match_sequential(database, matching_options=matching_options, device=pycolmap.Device.cpu)
        progress = get_progress("[bold yellow]Incremental mapping (images registered)")
        with progress:
            task = progress.add_task("mapping", total=len(names))
            models = pycolmap.incremental_mapping(
                database,
                image_dir,
                work_dir / "models",
                options=mapper,
                next_image_callback=lambda: progress.advance(task),
            )
            progress.update(task, completed=max((m.num_reg_images() for m in models.values()), default=0))
    if not models:
        raise SfmError(
            f"structure from motion registered none of the {len(names)} images in {image_dir}: too few "
            "SIFT matches between views (little overlap, blur, or texture-less water?)"
        )
    best = max(models.values(), key=lambda m: m.num_reg_images())
    registered = sorted(best.images[i].name for i in best.reg_image_ids())
    unregistered = sorted(set(names) - set(registered))
    return SfmResult(reconstruction=best, registered=registered, unregistered=unregistered)


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


def report(result: SfmResult) -> None:
    """Print how many images registered and name every one that did not."""
    total = len(result.registered) + len(result.unregistered)
    colour = "green" if not result.unregistered else ("yellow" if result.registration_rate >= 0.8 else "red")
    CONSOLE.print(
        f"[bold {colour}]Registered {len(result.registered)}/{total} images ({100 * result.registration_rate:.0f}%)"
    )
    if result.unregistered:
        CONSOLE.print(
            f"[bold yellow]Warning: {len(result.unregistered)} image(s) did not register and are left out of "
            f"transforms.json and sparse/0: {', '.join(result.unregistered)}"
        )
