"""The backscatter from the dark envelope of the whole scene (Sea-thru's estimate, Akkaynak &
Treibitz, CVPR 2019, sec. 4.3), read from the SfM observations before any training.

A surface at range ``z`` shows ``I = J e^{-β_D z} + B∞ (1 - e^{-β_B z})`` with ``J >= 0``, so every
pixel lies on or above the backscatter ``B(z) = B∞ (1 - e^{-β_B z})``, and the darkest surfaces at
each range lie close to it. Binned by range over the whole scene, the lower ``quantile`` of each
channel traces ``D(z) = B∞ (1 - e^{-β_B z}) + J' e^{-β_D' z}``, where the second term is what is
left of the dark surfaces' own light (Sea-thru's residual term).

Why the whole scene: the medium fit (:mod:`seathru_nerfstudio.medium_fit`) reads the change of a
point's colour between views, which only the range *change* between views drives (a few per cent on
a forward-facing rig); the envelope reads the range variation across the scene (a reef's 1.5–12 m),
but it needs dark surfaces at many ranges and a uniform light.

Units: ranges in world units (metres for metric captures), densities per world unit, colours linear.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares


@dataclass(frozen=True)
class Envelope:
    """The dark envelope per channel and its fit ``D(z) = B∞ (1 - e^{-β_B z}) + J' e^{-β_D' z}``."""

    ranges: npt.NDArray[np.float64]
    """(K,) bin centres (median range of each bin), world units."""
    dark: npt.NDArray[np.float64]
    """(K, 3) lower quantile of each channel in each bin."""
    veil: npt.NDArray[np.float64]
    """(3,) ``B∞``."""
    beta_B: npt.NDArray[np.float64]
    """(3,) ``β_B`` per world unit."""
    residual_light: npt.NDArray[np.float64]
    """(3,) ``J'``: the dark surfaces' light at range 0."""
    residual_decay: npt.NDArray[np.float64]
    """(3,) ``β_D'`` per world unit."""

    def backscatter(self, z: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """``B∞ (1 - e^{-β_B z})`` at ranges ``z`` (shape ``(*z, 3)``)."""
        z = np.asarray(z, dtype=np.float64)[..., None]
        return self.veil * -np.expm1(-self.beta_B * z)


def dark_envelope(
    ranges: npt.NDArray[np.floating], colours: npt.NDArray[np.floating], num_bins: int = 10, quantile: float = 0.01
) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Bin observations by range (equal counts per bin) and take each channel's ``quantile``.

    ``ranges``: (N,) world units; ``colours``: (N, 3) linear. Non-finite or non-positive ranges and
    non-finite colours are left out. Returns the bins' median ranges (K,) and dark values (K, 3),
    ``K <= num_bins`` (fewer where there are fewer than 3 observations a bin)."""
    if num_bins < 2 or not 0.0 < quantile < 1.0:
        raise ValueError(f"dark_envelope: need num_bins >= 2 and 0 < quantile < 1 (got {num_bins}, {quantile})")
    ranges = np.asarray(ranges, dtype=np.float64).reshape(-1)
    colours = np.asarray(colours, dtype=np.float64).reshape(-1, 3)
    keep = np.isfinite(ranges) & (ranges > 0) & np.isfinite(colours).all(axis=-1)
    ranges, colours = ranges[keep], colours[keep]
    order = np.argsort(ranges)
    bins = [b for b in np.array_split(order, min(num_bins, len(order) // 3)) if len(b)] if len(order) >= 6 else []
    if len(bins) < 2:
        raise ValueError(f"dark_envelope: {len(ranges)} usable observations; need at least 6")
    centres = np.array([np.median(ranges[b]) for b in bins])
    dark = np.array([np.quantile(colours[b], quantile, axis=0) for b in bins])
    return centres, dark


def fit_envelope(
    ranges: npt.NDArray[np.float64], dark: npt.NDArray[np.float64], veil: Optional[npt.ArrayLike] = None
) -> Envelope:
    """Fit ``D(z) = B∞ (1 - e^{-β_B z}) + J' e^{-β_D' z}`` to a dark envelope, per channel, by bounded
    least squares (``0 <= B∞ <= 1``, ``0 <= J' <= 1``, densities in ``[0, 50 / max z]``). ``veil``: a
    known ``B∞`` (e.g. the open water's colour), held instead of fitted; the envelope alone trades
    ``B∞`` against ``β_B`` where the ranges do not reach saturation.

    Densities are fitted as ``z_max β`` (unitless), so the fit does not depend on the unit."""
    z = np.asarray(ranges, dtype=np.float64)
    scale = float(z.max())
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError("fit_envelope: ranges must be finite and positive")
    t = z / scale
    fitted = []
    for channel in range(3):
        d = np.asarray(dark[:, channel], dtype=np.float64)

        held = None if veil is None else float(np.asarray(veil, dtype=np.float64)[channel])

        def residual(p: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
            b, beta_b, light, decay = (held, *p) if held is not None else p
            return b * -np.expm1(-beta_b * t) + light * np.exp(-decay * t) - d

        low, high = [0.0, 0.0, 0.0, 0.0], [1.0, 50.0, 1.0, 50.0]
        best = None
        for beta_start in (0.3, 3.0, 20.0):  # a few starts: the exponentials make it non-convex
            start = [min(max(d.max(), 1e-3), 1.0), beta_start, max(d.min(), 0.0) * 0.5, 1.0]
            if held is not None:
                start, bounds = start[1:], (low[1:], high[1:])
            else:
                bounds = (low, high)
            result = least_squares(residual, np.array(start), bounds=bounds)
            if best is None or result.cost < best.cost:
                best = result
        fitted.append(best.x if held is None else np.concatenate([[held], best.x]))
    p = np.array(fitted)
    return Envelope(
        ranges=z, dark=np.asarray(dark, dtype=np.float64), veil=p[:, 0], beta_B=p[:, 1] / scale,
        residual_light=p[:, 2], residual_decay=p[:, 3] / scale,
    )  # fmt: skip
