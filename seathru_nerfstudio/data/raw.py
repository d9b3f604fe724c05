"""RAW decoding and white balance, all in linear camera RGB.

Conventions
-----------
* Every image in this module is ``float32 (H, W, 3)`` **linear** camera RGB in [0, 1]: no
  gamma, no tone curve, no colour matrix (the sensor's own primaries, as SeaThru-NeRF's
  image formation model needs: ``I = J·T + B∞·(1 − T)`` only holds for linear values).
* RAW files are decoded with LibRaw (rawpy): black level subtracted, scaled so the sensor's
  white level is 1.0, demosaiced (AHD), ``gamma=(1, 1)``, ``no_auto_bright``, 16 bits out,
  and unit channel multipliers (no white balance) unless the camera's as-shot white
  balance is asked for. ``user_flip=0``: frames stay in sensor orientation, so a whole
  capture shares one image size and one set of intrinsics; NeRF does not care which way
  is up.
* White balance follows the paper (Sec. 5: "white-balanced ... with 0.5% clipping per
  channel"): each channel is clipped at its 0.5% / 99.5% percentiles and multiplied by a
  gain. Percentiles and gains are computed **jointly over the whole image set**, so every
  view gets the same gains and the views stay photometrically consistent. Only gains are
  applied, never an offset: an offset would change the medium's backscatter colour.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, Sequence

import cv2
import numpy as np
import numpy.typing as npt
import rawpy

from seathru_nerfstudio.data.io import to_uint16

# linear_images (and with it torch + nerfstudio) is imported only when a TIFF/PNG is read,
# so seathru-process-data starts, answers --help and rejects bad input in about a second.

RAW_EXTENSIONS = frozenset(
    ".nef .nrw .dng .cr2 .cr3 .crw .arw .srf .sr2 .raf .orf .rw2 .rwl .pef .srw .3fr .iiq .erf .kdc .dcr .mef .mos .x3f".split()
)
"""RAW formats handed to LibRaw (matched case-insensitively)."""
LINEAR_EXTENSIONS = frozenset({".tif", ".tiff", ".png"})
"""Already-decoded formats; they must hold 16-bit integer or float linear data."""

WhiteBalanceMethod = Literal["percentile", "grey-world", "camera", "none"]

HISTOGRAM_BINS = 65536
"""Histogram resolution for the joint percentiles: one bin per 16-bit code value."""


class RawDecodeError(ValueError):
    """A RAW file could not be decoded (corrupt, truncated or unsupported by LibRaw)."""


def is_raw(path: Path) -> bool:
    return path.suffix.lower() in RAW_EXTENSIONS


def decode_raw(path: Path | str, use_camera_wb: bool = False) -> npt.NDArray[np.float32]:
    """Decode a RAW file to linear camera RGB, float32 ``(H, W, 3)`` in [0, 1].

    1.0 is the sensor's white level (LibRaw's ``adjust_maximum_thr`` is off, so the scale
    does not depend on the brightest pixel of each frame). Without ``use_camera_wb`` the
    channel multipliers are all 1: the output is what the sensor measured. With it, LibRaw
    applies the as-shot multipliers and clips what they push above 1.
    """
    path = Path(path)
    wb = {"use_camera_wb": True} if use_camera_wb else {"user_wb": [1.0, 1.0, 1.0, 1.0]}
    try:
        with rawpy.imread(str(path)) as raw:
            rgb = raw.postprocess(
                gamma=(1, 1),
                no_auto_bright=True,
                output_bps=16,
                output_color=rawpy.ColorSpace.raw,
                use_auto_wb=False,
                adjust_maximum_thr=0.0,
                user_flip=0,
                **wb,
            )
    except (rawpy.LibRawError, OSError, ValueError) as error:
        raise RawDecodeError(f"{path}: cannot decode RAW file ({type(error).__name__}: {error})") from error
    return rgb.astype(np.float32) / 65535.0


def read_input_image(path: Path | str, use_camera_wb: bool = False) -> npt.NDArray[np.float32]:
    """Read one capture as linear RGB float32 ``(H, W, 3)``: RAW via :func:`decode_raw`,
    16-bit/float TIFF or PNG via :func:`read_linear_image` (alpha dropped).

    8-bit files are refused: they are display-referred (sRGB gamma, tone curve), not linear,
    and would silently bias the medium estimate. Raises :class:`RawDecodeError` or
    ``linear_images.ImageReadError``, both ``ValueError`` naming the file.
    """
    path = Path(path)
    if is_raw(path):
        return decode_raw(path, use_camera_wb=use_camera_wb)
    from seathru_nerfstudio.data.linear_images import ImageReadError, read_linear_image

    if path.suffix.lower() not in LINEAR_EXTENSIONS:
        raise ImageReadError(f"{path}: unsupported file type (expected RAW, 16-bit TIFF or PNG)")
    header = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if header is not None and header.dtype == np.uint8:
        raise ImageReadError(
            f"{path}: 8-bit image. 8-bit files are gamma-encoded for display, not linear; "
            "give the RAW files or 16-bit linear TIFF/PNG exports instead"
        )
    return read_linear_image(path)[..., :3]


def downscale_to_long_side(image: npt.NDArray[np.float32], max_long_side: int | None) -> npt.NDArray[np.float32]:
    """Shrink so the longer side is at most ``max_long_side`` px, by area averaging (a box
    filter: the mean of linear radiance, so linearity holds). Never upscales."""
    height, width = image.shape[:2]
    if max_long_side is None or max(height, width) <= max_long_side:
        return image
    scale = max_long_side / max(height, width)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


class ChannelHistogram:
    """Per-channel histogram of linear values over a whole image set, at 16-bit resolution,
    so joint percentiles are exact without holding every image in memory.

    Values are binned on [0, 1]; anything above 1 lands in the top bin.
    """

    def __init__(self, num_channels: int = 3) -> None:
        self.counts = np.zeros((num_channels, HISTOGRAM_BINS), dtype=np.int64)

    def add(self, image: npt.NDArray[np.floating]) -> None:
        codes = to_uint16(image).reshape(-1, image.shape[-1])
        for channel in range(self.counts.shape[0]):
            self.counts[channel] += np.bincount(codes[:, channel], minlength=HISTOGRAM_BINS)

    @property
    def num_pixels(self) -> int:
        return int(self.counts[0].sum())

    def percentile(self, percent: float) -> npt.NDArray[np.float64]:
        """Per-channel value below which ``percent`` % of all pixels lie (lower bin edge)."""
        cdf = np.cumsum(self.counts, axis=1)
        target = np.maximum(percent / 100.0 * cdf[:, -1], 1)
        codes = np.array([np.searchsorted(cdf[c], target[c]) for c in range(cdf.shape[0])])
        return codes.astype(np.float64) / 65535.0

    def clipped_mean(self, low: npt.NDArray[np.float64], high: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Per-channel mean after clipping channel ``c`` to ``[low[c], high[c]]``."""
        values = np.arange(HISTOGRAM_BINS, dtype=np.float64) / 65535.0
        clipped = np.clip(values[None, :], low[:, None], high[:, None])
        return (clipped * self.counts).sum(axis=1) / np.maximum(self.counts.sum(axis=1), 1)


@dataclass
class WhiteBalance:
    """Per-channel clip range and gains, shared by every image of a capture.

    ``apply`` computes ``clip(x_c, low_c, high_c) · gain_c`` in linear RGB; the gains are
    scaled so the brightest clipped value of any channel lands at exactly 1.0.
    """

    method: str
    clip_percent: float
    low: list[float]
    high: list[float]
    gains: list[float]

    @classmethod
    def identity(cls) -> "WhiteBalance":
        return cls(method="none", clip_percent=0.0, low=[0.0] * 3, high=[1.0] * 3, gains=[1.0] * 3)

    def apply(self, image: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        if self.method == "none":
            return image
        low, high, gains = (np.asarray(v, dtype=np.float32) for v in (self.low, self.high, self.gains))
        return np.clip(image, low, high) * gains

    def save(self, path: Path) -> None:
        path.write_text(json.dumps(asdict(self), indent=2) + "\n", encoding="utf-8")


def estimate_white_balance(
    histogram: ChannelHistogram, method: WhiteBalanceMethod = "percentile", clip_percent: float = 0.5
) -> WhiteBalance:
    """Joint white balance for an image set from its :class:`ChannelHistogram`.

    * ``percentile`` (the paper's): clip each channel at ``clip_percent`` / ``100 −
      clip_percent`` and map the upper percentile of every channel to 1.0
      (``gain_c = 1 / high_c``), i.e. a white patch at the 99.5% point becomes neutral.
    * ``grey-world``: same clipping, ``gain_c ∝ 1 / mean_c`` (the clipped scene averages to
      grey), scaled so the largest clipped value is 1.0.
    * ``camera``: the decode already applied the camera's as-shot multipliers; clip as
      above and apply one common gain so the brightest channel's upper percentile is 1.0.
    * ``none``: nothing, the decoded sensor values are written as they are.
    """
    if method == "none":
        return WhiteBalance.identity()
    if not 0.0 <= clip_percent < 50.0:
        raise ValueError(f"clip_percent must be in [0, 50), got {clip_percent}")
    if histogram.num_pixels == 0:
        raise ValueError("cannot white-balance an empty image set")
    low = histogram.percentile(clip_percent)
    high = histogram.percentile(100.0 - clip_percent)
    high = np.maximum(high, low + 1.0 / 65535.0)  # a flat channel must not divide by zero
    if method == "percentile":
        gains = 1.0 / high
    elif method == "grey-world":
        mean = np.maximum(histogram.clipped_mean(low, high), 1e-8)
        gains = 1.0 / mean
        gains = gains / np.max(gains * high)
    elif method == "camera":
        gains = np.full(3, 1.0 / np.max(high))
    else:
        raise ValueError(f"unknown white balance method {method!r}")
    return WhiteBalance(
        method=method,
        clip_percent=float(clip_percent),
        low=[float(v) for v in low],
        high=[float(v) for v in high],
        gains=[float(v) for v in gains],
    )


def image_sizes_summary(sizes: dict[str, Sequence[int]]) -> str:
    """``"4000x3000: a.NEF, b.NEF; 3000x4000: c.NEF"`` for an error message."""
    groups: dict[tuple[int, int], list[str]] = {}
    for name, (height, width) in sizes.items():
        groups.setdefault((int(width), int(height)), []).append(name)
    return "; ".join(f"{w}x{h}: {', '.join(names)}" for (w, h), names in sorted(groups.items()))
