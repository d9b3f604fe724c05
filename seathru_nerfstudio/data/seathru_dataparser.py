"""``seathru-data``: the published SeaThru-NeRF scenes (Curaçao, Panama, IUI3 Red Sea,
Japanese Gardens) and ``seathru-process-data`` output.

Layout::

    <data>/images_wb/ (or Images_wb/, or images/)   linear white-balanced images
    <data>/sparse/0/                                COLMAP model (OPENCV distortion)
    <data>/poses_bounds.npy                         LLFF, N×17, near/far per image (COLMAP units)

It is nerfstudio's ``ColmapDataParser`` with the published evaluation protocol:

* images ordered by file name; every 8th (index % 8 == 0) is a test view, the rest train;
* no automatic downscaling (nerfstudio's COLMAP parser halves anything wider than 1600 px):
  factor 1 unless ``--downscale-factor`` is given, and then only from an existing
  ``images_wb_<factor>/`` folder;
* near/far from ``poses_bounds.npy`` (or, without it, the same LLFF percentiles computed
  from the sparse points), scaled like the poses, in ``metadata``:
  ``near_far`` (N_split×2 tensor, scene units, rows follow ``image_filenames``) and the
  scalars ``near_plane`` / ``far_plane`` (min near, max far over all images) for a collider;
* a clear error naming the files when COLMAP's image names and the image folder disagree.

Image files are only listed here; the method's ``LinearImageDataset`` reads them at full
16-bit precision, linear, with no gamma.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Type

import numpy as np
import torch

from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.plugins.registry_dataparser import DataParserSpecification
from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio.data.input_checks import check_images
from seathru_nerfstudio.data.nerfstudio_data import EXTENT_KEY, SCALE_KEY, add_sfm_metadata, depths_from_colmap, frustum_extent
from seathru_nerfstudio.input_errors import InputError
from seathru_nerfstudio.metadata_keys import VERTICAL_KEY
from seathru_nerfstudio.vertical import scene_vertical

IMAGE_FOLDER_CANDIDATES = (Path("images_wb"), Path("Images_wb"), Path("images"))
IMAGE_SUFFIXES = frozenset({".png", ".tif", ".tiff", ".jpg", ".jpeg", ".exr"})


class SeathruDataError(InputError):
    """The dataset folder does not have the expected layout or its parts disagree."""


@dataclass
class SeathruDataParserConfig(ColmapDataParserConfig):
    """SeaThru-NeRF release layout (images_wb/, sparse/0, poses_bounds.npy)."""

    _target: Type = field(default_factory=lambda: SeathruDataParser)
    images_path: Path = Path("images_wb")
    """Image folder relative to data; if it is missing, Images_wb/ then images/ are tried."""
    colmap_path: Path = Path("sparse/0")
    """COLMAP model relative to data."""
    poses_bounds_path: Path = Path("poses_bounds.npy")
    """LLFF near/far file relative to data; without it near/far come from the sparse points."""
    downscale_factor: Optional[int] = 1
    """Image downscale factor. 1 (default): full resolution, never automatic. N > 1 needs an
    existing images_wb_N/ folder (nerfstudio would make one with 8-bit ffmpeg, destroying
    linear data); to shrink on the fly use --pipeline.datamanager.camera-res-scale-factor."""
    eval_interval: int = 8
    """Every eval_interval-th image (by sorted name, starting with the first) is a test view."""
    sfm_observations: bool = True
    """Build the table of the COLMAP points' colours across views for the model's ``medium_fit_step``."""


class SeathruDataParser(ColmapDataParser):
    """nerfstudio's COLMAP parser + name sorting, name checks, LLFF near/far, no auto-downscale."""

    config: SeathruDataParserConfig

    def _resolve_layout(self) -> None:
        data = self.config.data
        if not data.is_dir():
            raise SeathruDataError(f"dataset folder {data} does not exist")
        if not (data / self.config.images_path).is_dir():
            # only the default name falls back; a folder the user named must exist
            candidates = IMAGE_FOLDER_CANDIDATES if self.config.images_path == IMAGE_FOLDER_CANDIDATES[0] else ()
            found = next((p for p in candidates if (data / p).is_dir()), None)
            if found is None:
                raise SeathruDataError(
                    f"{data} has no image folder: looked for "
                    f"{', '.join(f'{p}/' for p in dict.fromkeys([self.config.images_path, *candidates]))}"
                )
            self.config.images_path = found
        if not (data / self.config.colmap_path).is_dir():
            raise SeathruDataError(f"{data} has no COLMAP model at {self.config.colmap_path}/")

    def _get_all_images_and_cameras(self, recon_dir: Path):
        """nerfstudio's frames, with file names checked against the image folder and sorted
        by COLMAP image name (the LLFF / published-split order)."""
        meta = super()._get_all_images_and_cameras(recon_dir)
        image_dir = self.config.data / self.config.images_path
        on_disk = {
            p.relative_to(image_dir).as_posix(): p
            for p in image_dir.rglob("*")
            if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
        }
        by_stem: dict[str, list[str]] = {}
        for name in on_disk:
            by_stem.setdefault(str(Path(name).with_suffix("")), []).append(name)
        missing, used = [], set()
        for frame in meta["frames"]:
            colmap_name = Path(frame["file_path"]).relative_to(image_dir).as_posix()
            frame["colmap_name"] = colmap_name
            match = colmap_name if colmap_name in on_disk else None
            if match is None:  # e.g. COLMAP ran on JPEGs, the linear images are PNG
                candidates = by_stem.get(str(Path(colmap_name).with_suffix("")), [])
                match = candidates[0] if len(candidates) == 1 else None
            if match is None:
                missing.append(colmap_name)
                continue
            frame["file_path"] = on_disk[match].as_posix()
            used.add(match)
        unused = sorted(set(on_disk) - used)
        if missing:
            raise SeathruDataError(
                f"image names in {recon_dir} and files in {image_dir} do not match.\n"
                f"  In COLMAP but not in {self.config.images_path}/ ({len(missing)}): {', '.join(sorted(missing))}\n"
                f"  In {self.config.images_path}/ but not in COLMAP ({len(unused)}): {', '.join(unused) or '-'}"
            )
        if unused:
            CONSOLE.print(
                f"[bold yellow]Warning: {len(unused)} image(s) in {image_dir} are not in the COLMAP model "
                f"and are not used: {', '.join(unused)}"
            )
        meta["frames"].sort(key=lambda frame: frame["colmap_name"])
        self._colmap_names = [frame["colmap_name"] for frame in meta["frames"]]
        self._colmap_centres = [np.asarray(frame["transform_matrix"])[:3, 3] for frame in meta["frames"]]
        return meta

    def _get_image_indices(self, image_filenames, split):
        indices = super()._get_image_indices(image_filenames, split)
        self._split_indices = np.asarray(indices, dtype=np.int64)
        return indices

    def _setup_downscale_factor(
        self, image_filenames: List[Path], mask_filenames: List[Path], depth_filenames: List[Path]
    ):
        factor = self.config.downscale_factor
        if factor is None:
            factor = self.config.downscale_factor = 1  # never guess: full resolution
        if factor > 1:
            folder = self.config.data / f"{self.config.images_path}_{factor}"
            if not folder.is_dir():
                raise SeathruDataError(
                    f"--downscale-factor {factor} needs {folder}/ (downscaled linear images, e.g. from "
                    "seathru-process-data --max-long-side). nerfstudio's automatic downscaling writes 8-bit "
                    "images, which breaks linear data; --pipeline.datamanager.camera-res-scale-factor "
                    f"{1 / factor:g} downsamples in memory at full precision instead"
                )
        return super()._setup_downscale_factor(image_filenames, mask_filenames, depth_filenames)

    def _near_far(self, recon_dir: Path) -> np.ndarray:
        """Per-image (near, far) in COLMAP units, in ``self._colmap_names`` order."""
        path = self.config.data / self.config.poses_bounds_path
        if path.is_file():
            poses_bounds = np.load(path)
            if poses_bounds.ndim != 2 or poses_bounds.shape[1] != 17:
                raise SeathruDataError(f"{path}: expected an N×17 LLFF array, got shape {poses_bounds.shape}")
            if len(poses_bounds) != len(self._colmap_names):
                raise SeathruDataError(
                    f"{path} has {len(poses_bounds)} rows but {recon_dir} has {len(self._colmap_names)} images; "
                    "LLFF stores one row per COLMAP image, sorted by name"
                )
            self._check_row_order(path, poses_bounds)
            return poses_bounds[:, 15:17].astype(np.float64)
        from seathru_nerfstudio.data.sfm_outputs import llff_poses_bounds, pycolmap  # cv2 before pycolmap (sfm.py)

        CONSOLE.print(f"[yellow]No {path.name}: near/far from the sparse points of {recon_dir} (LLFF percentiles)")
        names, rows = llff_poses_bounds(pycolmap.Reconstruction(str(recon_dir)))
        by_name = dict(zip(names, rows[:, 15:17]))
        return np.array([by_name[name] for name in self._colmap_names], dtype=np.float64)

    def _check_row_order(self, path: Path, poses_bounds: np.ndarray) -> None:
        """Warn when the LLFF rows do not line up with the COLMAP images sorted by name: the
        camera centres (column 3 of each 3×5 pose) must have COLMAP's pairwise distances."""
        llff = poses_bounds[:, :15].reshape(-1, 3, 5)[:, :, 3]
        ours = np.asarray(self._colmap_centres)
        distances = lambda x: np.linalg.norm(x[:, None] - x[None], axis=-1)  # noqa: E731
        error = np.abs(distances(llff) - distances(ours)).max(initial=0.0)
        if error > 1e-3 * max(distances(ours).max(initial=0.0), 1e-9):
            CONSOLE.print(
                f"[bold yellow]Warning: the camera centres in {path} do not match {self.config.colmap_path} "
                "(rows not in image-name order, or another COLMAP run): near/far may belong to other images"
            )

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        self._resolve_layout()
        outputs = super()._generate_dataparser_outputs(split, **kwargs)
        check_images(outputs.image_filenames, outputs.cameras.height.flatten().tolist(), outputs.cameras.width.flatten().tolist())
        near_far = self._near_far(self.config.data / self.config.colmap_path)
        if not np.all(np.isfinite(near_far)) or np.any(near_far[:, 0] <= 0) or np.any(near_far[:, 1] <= near_far[:, 0]):
            raise SeathruDataError(f"near/far bounds must satisfy 0 < near < far, got {near_far.tolist()}")
        scale = float(outputs.dataparser_scale)
        outputs.metadata["near_far"] = torch.from_numpy(near_far[self._split_indices] * scale).float()
        outputs.metadata["near_plane"] = float(near_far[:, 0].min() * scale)
        outputs.metadata["far_plane"] = float(near_far[:, 1].max() * scale)
        outputs.metadata[EXTENT_KEY] = frustum_extent(outputs.cameras, outputs.metadata["far_plane"])
        outputs.metadata[SCALE_KEY] = scale
        outputs.metadata[VERTICAL_KEY] = scene_vertical(outputs.cameras.camera_to_worlds).tolist()
        if not outputs.metadata.get("depth_filenames"):  # the model's tracks, as seathru-process-data gives them
            depths_from_colmap(outputs, self.config.data / self.config.colmap_path)
        add_sfm_metadata(outputs, split, self.config.sfm_observations, bounds=False)  # near/far: poses_bounds.npy
        return outputs


seathru_dataparser = DataParserSpecification(
    config=SeathruDataParserConfig(),
    description="SeaThru-NeRF release layout: images_wb/, sparse/0, poses_bounds.npy; every 8th image to test.",
)
