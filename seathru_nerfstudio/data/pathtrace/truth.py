"""The best-fitting SeaThru medium of a rendered scene: its veiling light ``B_inf`` and
backscatter coefficient ``beta_B`` given the true attenuation.

A path-traced scene has a physical medium (extinction ``sigma_t``, albedo, phase function),
not SeaThru's three numbers per channel. Its direct signal is attenuated exactly by
``exp(-sigma_t z)``, so ``beta_D = sigma_t``; the backscatter (multiple scattering, sun and sky
through the surface) only approximately follows ``B_inf (1 - exp(-beta_B z))``. The values that
any SeaThru-model method can reach are the least-squares fit of that formula to the renders::

    I  ~  J exp(-beta_D z) + B_inf (1 - exp(-beta_B z))        (per channel, z = range in m)

over the pixels that see an object (finite range). For fixed ``beta_B`` the best ``B_inf`` is in
closed form, ``B = sum(y f) / sum(f^2)`` with ``y = I - J exp(-beta_D z)`` and
``f = -expm1(-beta_B z)``; ``beta_B`` is searched on a log grid and refined by golden section.
"""

from __future__ import annotations

import math
from typing import Dict, Sequence

import numpy as np
import numpy.typing as npt

BETA_B_RANGE = (1e-3, 20.0)
"""Search interval of ``beta_B`` (1/m)."""
GRID_POINTS = 121
GOLDEN_STEPS = 40


def _profile(y: npt.NDArray[np.float64], z: npt.NDArray[np.float64], beta_b: float):
    """(sse, B) of the best ``B >= 0`` for one ``beta_B``: B = max(0, <y, f> / <f, f>)."""
    f = -np.expm1(-beta_b * z)
    ff = float(f @ f)
    b = max(0.0, float(y @ f) / ff) if ff > 0 else 0.0
    r = y - b * f
    return float(r @ r), b


def _fit_channel(y: npt.NDArray[np.float64], z: npt.NDArray[np.float64]):
    """(beta_B, B_inf, rmse) minimising ``sum (y - B (1 - exp(-beta_B z)))^2`` over beta_B in
    :data:`BETA_B_RANGE` (grid in log beta_B, then golden section between the grid neighbours)."""
    logs = np.linspace(math.log(BETA_B_RANGE[0]), math.log(BETA_B_RANGE[1]), GRID_POINTS)
    sse = np.array([_profile(y, z, math.exp(s))[0] for s in logs])
    k = int(np.argmin(sse))
    lo, hi = logs[max(k - 1, 0)], logs[min(k + 1, GRID_POINTS - 1)]
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    fa, fb = _profile(y, z, math.exp(a))[0], _profile(y, z, math.exp(b))[0]
    for _ in range(GOLDEN_STEPS):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = hi - ratio * (hi - lo)
            fa = _profile(y, z, math.exp(a))[0]
        else:
            lo, a, fa = a, b, fb
            b = lo + ratio * (hi - lo)
            fb = _profile(y, z, math.exp(b))[0]
    best = min([(fa, a), (fb, b), (float(sse[k]), float(logs[k]))])
    err, b_inf = _profile(y, z, math.exp(best[1]))
    return math.exp(best[1]), b_inf, math.sqrt(err / max(1, y.size))


def fit_veil_and_backscatter(
    images: Sequence[npt.ArrayLike], clean: Sequence[npt.ArrayLike], ranges: Sequence[npt.ArrayLike], beta_D: npt.ArrayLike
) -> Dict[str, object]:
    """Least-squares ``B_inf`` and ``beta_B`` per channel, given the true ``beta_D``.

    Args:
        images: in-medium linear images, each (H, W, 3) (or one (N, H, W, 3) array).
        clean: the matching J terms (H, W, 3), the radiance leaving the surfaces.
        ranges: (H, W) ranges in metres along each pixel's ray; ``inf`` (or non-finite) = open
            water, left out of the fit.
        beta_D: (3,) attenuation in 1/m (the medium's extinction ``sigma_t``).

    Returns:
        ``beta_B`` (3, 1/m), ``B_inf`` (3, linear image units), ``beta_D`` (3, as given),
        ``rmse`` (3, of the fit's residual), ``num_pixels`` (object pixels used) and
        ``open_water_mean`` (3, the mean image colour over open-water pixels; None if none).
    Raises ValueError on mismatched shapes or without any object pixel.
    """
    beta_d = np.asarray(beta_D, dtype=np.float64).reshape(3)
    obs, sig, z_all = [], [], []
    open_sum, open_count = np.zeros(3), 0
    for image, j, r in zip(images, clean, ranges, strict=True):
        image, j, r = np.asarray(image, np.float64)[..., :3], np.asarray(j, np.float64)[..., :3], np.asarray(r, np.float64)
        if image.shape != j.shape or image.shape[:2] != r.shape:
            raise ValueError(f"shapes differ: image {image.shape}, clean {j.shape}, range {r.shape}")
        known = np.isfinite(r) & (r > 0)
        obs.append(image[known])
        sig.append(j[known])
        z_all.append(r[known])
        open_sum += image[~np.isfinite(r)].sum(axis=0)
        open_count += int(np.sum(~np.isfinite(r)))
    z = np.concatenate(z_all) if z_all else np.zeros(0)
    if z.size == 0:
        raise ValueError("no pixel with a finite range: nothing to fit")
    observed, signal = np.concatenate(obs), np.concatenate(sig)
    result: Dict[str, list] = {"beta_B": [], "B_inf": [], "rmse": []}
    for c in range(3):
        y = observed[:, c] - signal[:, c] * np.exp(-beta_d[c] * z)
        beta_b, b_inf, rmse = _fit_channel(y, z)
        result["beta_B"].append(beta_b)
        result["B_inf"].append(b_inf)
        result["rmse"].append(rmse)
    return {
        **result,
        "beta_D": beta_d.tolist(),
        "num_pixels": int(z.size),
        "open_water_mean": (open_sum / open_count).tolist() if open_count else None,
    }
