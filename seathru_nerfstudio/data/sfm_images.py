"""The display copies structure from motion runs on: what SIFT sees of a linear image.

Linear underwater frames are dark and flat, and a medium veils far texture, so SIFT's contrast
threshold finds few features in them. :func:`write_display_copy` writes an 8-bit copy that lifts
the shadows (:func:`display_transform`) and equalises the lightness region by region
(:func:`feature_image`). The copies are used for poses only, never for training.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

DISPLAY_GAMMA = 2.2


def display_transform(image: npt.NDArray[np.floating], percentile: float = 99.5) -> npt.NDArray[np.uint8]:
    """Linear RGB -> 8-bit display RGB for feature detection only (never for training).

    Divides by the image's own ``percentile`` value (over all channels), clips, and applies
    gamma ``1 / 2.2``; this lifts the shadows where underwater texture lives.
    """
    step = max(1, max(image.shape[:2]) // 1024)  # a strided sample is plenty for one percentile
    white = float(np.percentile(image[::step, ::step], percentile))
    normalised = np.clip(image / max(white, 1e-6), 0.0, 1.0)
    return np.round(normalised ** (1.0 / DISPLAY_GAMMA) * 255.0).astype(np.uint8)


FEATURE_BLUR_PX = 1.0
"""Gaussian σ, in pixels, of the blur before SIFT. COLMAP detects from an image upsampled 2×,
where per-pixel noise (high ISO, or a path tracer's samples) makes features that match nothing."""
CONTRAST_TILES = 4
"""Local contrast equalisation (CLAHE) works on this many tiles along each side of the image."""
CONTRAST_CLIP = 2.0
"""CLAHE's clip limit: a tile's histogram is clipped at this multiple of its mean bin count,
which bounds how much a flat tile's noise is amplified (OpenCV's usual value)."""


def feature_image(display: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """The display copy SIFT sees: blurred by :data:`FEATURE_BLUR_PX`, then its lightness
    equalised tile by tile (CLAHE, :data:`CONTRAST_TILES`, :data:`CONTRAST_CLIP`).

    Why: a medium adds a veil that grows with range and scales the texture behind it by
    ``e^{-β_D z}``, so far texture is a few grey levels on a bright offset; one tone curve for the
    whole image cannot lift it, a per-region equalisation can. On the path-traced scenes
    (240×160, 256 spp; docs/data.md) coastal water goes from 0/24 images registered to 23/24
    (median rotation error 1.6°), fog from 16/24 (5.9°) to 24/24 (1.0°), clear air stays 24/24
    (0.27° to 0.21°). Neither step alone registers coastal water (CLAHE alone: 5/24)."""
    blurred = cv2.GaussianBlur(display, (0, 0), FEATURE_BLUR_PX)
    lab = cv2.cvtColor(blurred, cv2.COLOR_RGB2LAB)
    equalise = cv2.createCLAHE(clipLimit=CONTRAST_CLIP, tileGridSize=(CONTRAST_TILES, CONTRAST_TILES))
    lab[..., 0] = equalise.apply(np.ascontiguousarray(lab[..., 0]))
    return cv2.cvtColor(lab, cv2.COLOR_LAB2RGB)


def write_display_copy(path: Path, image: npt.NDArray[np.floating]) -> None:
    """Write :func:`feature_image` of :func:`display_transform` of a linear RGB image as an 8-bit
    PNG, the copy structure from motion runs on."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), feature_image(display_transform(image))[..., ::-1]):
        raise OSError(f"{path}: could not write image")
