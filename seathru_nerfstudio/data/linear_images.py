"""Full-precision image loading: 16-bit PNG/TIFF stay 16-bit from disk to loss.

nerfstudio's ``InputDataset`` reads every image through PIL and casts it to uint8, which
throws away the low byte of 16-bit linear captures (the dark half of an underwater frame).
:class:`LinearImageDataset` reads them at full precision instead, and also carries the ground
truth that the dataparser declares per frame (:mod:`seathru_nerfstudio.data.ground_truth`)
into the batches.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional

import cv2
import numpy as np
import numpy.typing as npt
import torch
from jaxtyping import Float
from torch import Tensor

from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.utils.data_utils import get_depth_image_from_path
from seathru_nerfstudio.data.ground_truth import GT_CLEAN_FILENAMES, GT_DEPTH_FILENAMES
from seathru_nerfstudio.input_errors import InputError


class ImageReadError(InputError):
    """An image file is missing, unreadable or of an unsupported layout."""


def read_linear_image(path: Path | str, scale_factor: float = 1.0) -> npt.NDArray[np.float32]:
    """Read an image as float32 ``(H, W, 3 or 4)`` in [0, 1], keeping every bit.

    uint8 is divided by 255, uint16 by 65535; float images (TIFF/EXR) are returned as they
    are. Grey images become 3 channels. Colour order is RGB(A). No gamma is applied or
    removed: a linear file gives linear values. ``scale_factor`` resizes with area averaging,
    which preserves linear radiance.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageReadError(f"{path}: no such image file")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ImageReadError(f"{path}: not a readable image (corrupt or unsupported format)")
    if raw.dtype == np.uint8:
        image = raw.astype(np.float32) / 255.0
    elif raw.dtype == np.uint16:
        image = raw.astype(np.float32) / 65535.0
    elif raw.dtype in (np.float32, np.float64):
        image = raw.astype(np.float32)
    else:
        raise ImageReadError(f"{path}: unsupported pixel type {raw.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ImageReadError(f"{path}: expected 1, 3 or 4 channels, got shape {raw.shape}")
    # OpenCV stores BGR(A); nerfstudio wants RGB(A).
    image = image[:, :, [2, 1, 0, 3][: image.shape[2]]]
    if scale_factor != 1.0:
        height, width = image.shape[:2]
        size = (int(width * scale_factor), int(height * scale_factor))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(image)


def read_range_map(path: Path | str) -> npt.NDArray[np.float32]:
    """A ground-truth range map: ``.npy``, ``H x W`` (or ``H x W x 1``), float; ``inf`` = open water."""
    path = Path(path)
    if not path.is_file():
        raise ImageReadError(f"{path}: no such ground-truth depth file")
    try:
        depth = np.load(path, allow_pickle=False)
    except ValueError as error:
        raise ImageReadError(f"{path}: not a .npy array ({error})") from error
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[:, :, 0]
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        raise ImageReadError(f"{path}: expected a float H x W range map, got {depth.dtype} of shape {depth.shape}")
    return depth.astype(np.float32)


class LinearImageDataset(InputDataset):
    """An ``InputDataset`` that loads 8- and 16-bit images at full precision.

    Batches gain ``gt_clean`` (linear RGB) and ``gt_depth`` (range from the camera centre,
    in scene units: world units times the dataparser scale; ``inf`` for open water) when the
    dataparser's metadata lists ground-truth files (``gt_clean_filenames``,
    ``gt_depth_filenames``), and ``depth_image`` (z-depth in scene units, 0 = unknown; e.g.
    sparse SfM depths) when its frames have nerfstudio's ``depth_file_path``, read as
    nerfstudio's ``DepthDataset`` reads them.
    """

    def get_image_float32(self, image_idx: int) -> Float[Tensor, "image_height image_width num_channels"]:
        filename = self._dataparser_outputs.image_filenames[image_idx]
        image = torch.from_numpy(read_linear_image(filename, self.scale_factor))
        alpha_color = self._dataparser_outputs.alpha_color
        if alpha_color is not None and image.shape[-1] == 4:
            image = image[:, :, :3] * image[:, :, -1:] + alpha_color * (1.0 - image[:, :, -1:])
        return image

    def get_numpy_image(self, image_idx: int) -> npt.NDArray[np.uint8]:
        """An 8-bit copy, for the few nerfstudio paths that want one (never for training)."""
        filename = self._dataparser_outputs.image_filenames[image_idx]
        image = read_linear_image(filename, self.scale_factor)
        return np.clip(np.round(image * 255.0), 0, 255).astype(np.uint8)

    def get_metadata(self, data: Dict) -> Dict:
        index = data["image_idx"]
        declared = self._dataparser_outputs.metadata
        metadata: Dict[str, Optional[Tensor]] = {}
        if declared.get(GT_CLEAN_FILENAMES):
            clean = read_linear_image(declared[GT_CLEAN_FILENAMES][index], self.scale_factor)
            metadata["gt_clean"] = torch.from_numpy(clean[..., :3])
        if declared.get(GT_DEPTH_FILENAMES):
            depth = read_range_map(declared[GT_DEPTH_FILENAMES][index])
            if self.scale_factor != 1.0:
                height, width = depth.shape[:2]
                size = (int(width * self.scale_factor), int(height * self.scale_factor))
                depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
            scale = float(self._dataparser_outputs.dataparser_scale)
            metadata["gt_depth"] = torch.from_numpy(depth * scale)[..., None]
        depth_filenames = declared.get("depth_filenames")
        if depth_filenames:
            camera = self._dataparser_outputs.cameras[index]
            metadata["depth_image"] = get_depth_image_from_path(
                filepath=Path(depth_filenames[index]),
                height=int(camera.height),
                width=int(camera.width),
                scale_factor=float(self._dataparser_outputs.metadata["depth_unit_scale_factor"])
                * float(self._dataparser_outputs.dataparser_scale),
            )
        return metadata
