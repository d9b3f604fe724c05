"""The ceiling of a scene: the SeaThru formation model inverted with the true range and the
best-fitting medium. No method that explains an image with this model can recover the clean
image J better than this (up to the fit's choice of loss), so every J score is read beside it.

The model, per channel ``c`` and pixel, with the range ``z`` in metres and the densities in 1/m::

    I = J e^{-β_D z} + B∞ (1 − e^{-β_B z})                                   (1)

Inverted with the true ``z``::

    Ĵ = (I − B∞ (1 − e^{-β_B z})) e^{β_D z}                                   (2)

Numerics: ``1 − e^{-x}`` is ``-expm1(-x)``; a density of 0 times an infinite range is 0 (clear
air has no backscatter, never ``0·inf``); the gain ``e^{β_D z}`` is capped at
``e^{MAX_LOG_GAIN}`` (about 1e300), so that (2) is finite for every finite input. A capped
pixel's direct signal is below 1e-300 of its J: no image carries it, and its Ĵ is as
meaningless as any; :func:`invert` counts them, and callers report that count. Open water
(``z = inf``) has no J: Ĵ is 0 there (``seathru-synth``'s convention) and no score reads it.

Pure functions of float64 numpy arrays; shapes in the annotations (``...`` any batch shape,
``N`` pixels, ``3`` channels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Tuple

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

Array = npt.NDArray[np.float64]

MAX_LOG_GAIN = 690.0
"""Largest exponent ``β_D z`` of the inversion's gain (``e^690 ≈ 1e300``, below float64's 1.8e308,
so the gain times any image value up to 1e7 stays finite)."""



def optical_depth(beta: Array, z: Array) -> Array:
    """``β z`` of each pixel and channel: ``beta`` ``(3,)`` in 1/m, ``z`` ``(...)`` in m -> ``(..., 3)``.

    ``0 · inf = 0``: clear air has no optical depth, however far it reaches.
    """
    beta = np.asarray(beta, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)[..., None]
    return beta * np.where(beta == 0.0, 0.0, z)


def backscatter_fraction(beta_B: Array, z: Array) -> Array:
    """``1 − e^{-β_B z}`` as ``-expm1(-β_B z)``: ``(...)`` ranges -> ``(..., 3)``, in [0, 1]; 1 at
    ``z = inf`` in water, 0 in clear air at any range."""
    return -np.expm1(-optical_depth(beta_B, z))


def form_image(J: Array, z: Array, beta_D: Array, beta_B: Array, B_inf: Array) -> Array:
    """Equation (1): ``J`` ``(..., 3)``, ``z`` ``(...)`` (m, ``inf`` = open water) -> ``I`` ``(..., 3)``.

    Open water (``z = inf``) gives ``I = B∞ (1 − e^{-β_B·inf})``, ``B∞`` in water, whatever J is.
    """
    transmission = np.exp(-optical_depth(beta_D, z))
    direct = np.where(np.isfinite(z)[..., None], np.asarray(J, dtype=np.float64) * transmission, 0.0)
    return direct + np.asarray(B_inf, dtype=np.float64) * backscatter_fraction(beta_B, z)


def invert(I: Array, z: Array, beta_D: Array, beta_B: Array, B_inf: Array) -> Tuple[Array, int]:
    """Equation (2): ``I`` ``(..., 3)``, ``z`` ``(...)`` (m) -> (``Ĵ`` ``(..., 3)``, number of
    capped pixel channels).

    Finite for finite ``I``: the gain's exponent ``β_D z`` is capped at :data:`MAX_LOG_GAIN` (the
    count of capped values is returned); ``Ĵ = 0`` in open water. Not clipped: a score clips it
    to [0, 1] as it clips every estimate.
    """
    finite = np.isfinite(z)[..., None]
    zf = np.where(np.isfinite(z), z, 0.0)
    exponent = optical_depth(beta_D, zf)
    capped = int(np.count_nonzero(finite & (exponent > MAX_LOG_GAIN)))
    signal = np.asarray(I, dtype=np.float64) - np.asarray(B_inf, dtype=np.float64) * backscatter_fraction(beta_B, zf)
    J_hat = np.where(finite, signal * np.exp(np.minimum(exponent, MAX_LOG_GAIN)), 0.0)
    return J_hat, capped


@dataclass(frozen=True)
class MediumFit:
    """A least-squares fit of (1), per channel: densities in 1/m, ``B_inf`` linear, ``rms`` the
    root-mean-square residual of ``I`` (linear units) over the fitted pixels."""

    beta_D: Tuple[float, float, float]
    beta_B: Tuple[float, float, float]
    B_inf: Tuple[float, float, float]
    rms: Tuple[float, float, float]
    num_pixels: int

    def as_dict(self) -> dict:
        return {k: list(getattr(self, k)) for k in ("beta_D", "beta_B", "B_inf", "rms")} | {"num_pixels": self.num_pixels}


def _flatten(I: Array, J: Array, z: Array) -> Tuple[Array, Array, Array]:
    """Object pixels only: ``I``, ``J`` ``(..., 3)`` and ``z`` ``(...)`` -> ``(N, 3), (N, 3), (N,)``."""
    objects = np.isfinite(z)
    if not np.any(objects):
        raise ValueError("no object pixel (every range is inf): nothing to fit")
    return (
        np.asarray(I, dtype=np.float64)[objects][:, :3],
        np.asarray(J, dtype=np.float64)[objects][:, :3],
        np.asarray(z, dtype=np.float64)[objects],
    )


def fit_backscatter(I: Array, J: Array, z: Array, beta_D: Array) -> MediumFit:
    """β_B, B∞ of (1) by least squares over the object pixels (finite ``z``), with ``J`` and ``z``
    true and ``β_D`` given: ``I``, ``J`` ``(..., 3)`` linear, ``z`` ``(...)`` m, ``beta_D`` ``(3,)`` 1/m.

    Per channel, ``r = I − J e^{-β_D z}`` is what the backscatter must explain, and
    ``min Σ (r − B∞ (1 − e^{-β_B z}))²`` is solved exactly in ``B∞ ≥ 0`` for each ``β_B``, which is
    searched on a log grid and refined: the path-traced scenes' fit,
    :func:`seathru_nerfstudio.data.pathtrace.truth.fit_veil_and_backscatter` (one fit for both).
    Without any backscatter (``r ≡ 0``: clear air) ``B∞ = 0`` and β_B is the search's lower end.
    """
    from seathru_nerfstudio.data.pathtrace.truth import fit_veil_and_backscatter

    I, J, z = _flatten(I, J, z)
    fit = fit_veil_and_backscatter([I[None]], [J[None]], [z[None]], np.asarray(beta_D, dtype=np.float64))
    return MediumFit(
        beta_D=tuple(float(b) for b in fit["beta_D"]),  # type: ignore[arg-type]
        beta_B=tuple(float(b) for b in fit["beta_B"]),  # type: ignore[arg-type]
        B_inf=tuple(float(b) for b in fit["B_inf"]),  # type: ignore[arg-type]
        rms=tuple(float(r) for r in fit["rmse"]),  # type: ignore[arg-type]
        num_pixels=int(fit["num_pixels"]),
    )


def fit_medium(I: Array, J: Array, z: Array, start: MediumFit) -> MediumFit:
    """β_D, β_B and B∞ of (1), all three by least squares over the object pixels, per channel,
    from ``start`` (e.g. :func:`fit_backscatter` at the true β_D); β_D and B∞ bounded below by 0,
    β_B searched where :func:`fit_backscatter` searches it (``truth.BETA_B_RANGE``: beyond, the
    backscatter is saturated at every range and β_B no longer changes the image).

    Residual ``J e^{-β_D z} + B∞ (1 − e^{-β_B z}) − I`` with the Jacobian
    ``(−z J e^{-β_D z}, B∞ z e^{-β_B z}, 1 − e^{-β_B z})``; scipy's trust-region reflective solver.
    """
    from seathru_nerfstudio.data.pathtrace.truth import BETA_B_RANGE

    I, J, z = _flatten(I, J, z)
    out = []
    for c in range(3):
        Ic, Jc = I[:, c], J[:, c]

        def residual(p: Array) -> Array:
            return Jc * np.exp(-p[0] * z) + p[2] * -np.expm1(-p[1] * z) - Ic

        def jacobian(p: Array) -> Array:
            return np.stack([-z * Jc * np.exp(-p[0] * z), p[2] * z * np.exp(-p[1] * z), -np.expm1(-p[1] * z)], axis=1)

        x0 = np.array([start.beta_D[c], start.beta_B[c], start.B_inf[c]], dtype=np.float64)
        lower, upper = np.array([0.0, BETA_B_RANGE[0], 0.0]), np.array([np.inf, BETA_B_RANGE[1], np.inf])
        x0 = np.clip(x0, lower, upper)
        result = least_squares(
            residual, x0, jac=jacobian, bounds=(lower, upper),
            method="trf", x_scale="jac", ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=500,
        )  # fmt: skip
        res = residual(result.x)
        out.append((*[float(v) for v in result.x], math.sqrt(float(np.dot(res, res)) / len(z))))
    return MediumFit(
        beta_D=tuple(o[0] for o in out),  # type: ignore[arg-type]
        beta_B=tuple(o[1] for o in out),  # type: ignore[arg-type]
        B_inf=tuple(o[2] for o in out),  # type: ignore[arg-type]
        rms=tuple(o[3] for o in out),  # type: ignore[arg-type]
        num_pixels=len(z),
    )
