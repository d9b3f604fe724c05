"""The statistical standard errors of the medium fit's log-densities
(:mod:`~seathru_nerfstudio.medium_fit`), from the curvature of its residual, given the veiling
light. How far ``β_B`` moves when that veil is off is another matter, and usually the larger
error: :func:`~seathru_nerfstudio.medium_fit.veil_sensitivity`.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


LOG_DENSITY_LIMIT = 20.7
"""The fitted densities are clamped to ``e^{±20.7}`` ≈ 1e-9 to 1e9 per world unit: a channel the
observations say nothing about may run off towards 0 or infinity."""


def log_density_errors(
    squared_error: Float[Tensor, "3"],
    hessian: Float[Tensor, "6 6"],
    num_points: int,
) -> tuple[Float[Tensor, "3"], Float[Tensor, "3"]]:
    """Standard errors of ``(ln β_D, ln β_B)`` per channel from the curvature of the residual.

    ``squared_error[c]`` is channel c's sum of squared residuals ``S_c`` at the fit and
    ``hessian`` the Hessian of ``Σ_c S_c`` in ``(ln β_D, ln β_B)`` (block-diagonal: the channels
    do not interact). Gauss–Newton gives ``cov_c = 2 σ_c² H_c⁻¹`` (``H = 2 JᵀJ``). A point's
    residuals across its views share its errors (its colour, its position), so ``σ_c² = S_c /
    num_points``: one independent residual per point, not per observation. A block that is not
    positive definite (a flat direction) gets the largest error, ``2 × LOG_DENSITY_LIMIT``."""
    worst = 2 * LOG_DENSITY_LIMIT
    attenuation_error = torch.full((3,), worst, dtype=torch.float64)
    backscatter_error = attenuation_error.clone()
    for c in range(3):
        block = hessian[[c, c + 3]][:, [c, c + 3]].double()
        determinant = block[0, 0] * block[1, 1] - block[0, 1] ** 2
        if not (torch.isfinite(block).all() and block[0, 0] > 0 and determinant > 0) or num_points < 1:
            continue
        # 2 S / n · H⁻¹'s diagonal, divided last: S = 0 over a tiny determinant gives 0, never 0·inf
        variance = 2.0 * squared_error[c].double() / num_points * torch.stack([block[1, 1], block[0, 0]]) / determinant
        errors = torch.sqrt(torch.clamp(variance, min=0.0)).clamp(max=worst)
        attenuation_error[c], backscatter_error[c] = errors[0], errors[1]
    return attenuation_error, backscatter_error


def tied_log_density_errors(
    squared_error: Float[Tensor, "3"],
    channel_hessians: Float[Tensor, "3 K K"],
    tie: Float[Tensor, "6 K"],
    num_points: int,
) -> tuple[Float[Tensor, "3"], Float[Tensor, "3"]]:
    """:func:`log_density_errors` where channels share free log-densities (``tie``, see
    :func:`tie_matrix`): the channels' information adds up, ``cov = (Σ_c H_c / (2 σ_c²))⁻¹`` with
    ``σ_c² = S_c / num_points`` and ``H_c`` the Hessian of ``S_c`` in the free parameters; each
    density gets the error of the free parameter it is. Untied, this is :func:`log_density_errors`
    block by block. Not positive definite: every density gets ``2 × LOG_DENSITY_LIMIT``."""
    worst = torch.full((6,), 2 * LOG_DENSITY_LIMIT, dtype=torch.float64)
    hessians, squared = channel_hessians.double(), squared_error.double()
    if num_points >= 1 and torch.isfinite(hessians).all() and torch.isfinite(squared).all():
        # S_c = 0 (exact data) is floored far below any real residual: its channel then pins the fit
        variance = torch.clamp(squared, min=1e-30 * num_points) / num_points
        information = (hessians / (2.0 * variance[:, None, None])).sum(dim=0)
        factor, singular = torch.linalg.cholesky_ex(information)
        if int(singular) == 0:
            covariance = torch.cholesky_inverse(factor)
            per_density = torch.einsum("dk,kl,dl->d", tie.double(), covariance, tie.double())
            worst = torch.sqrt(torch.clamp(per_density, min=0.0)).clamp(max=2 * LOG_DENSITY_LIMIT)
    return worst[:3], worst[3:]

