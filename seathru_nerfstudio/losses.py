"""Losses of SeaThru-NeRF (sec. 3.5): RawNeRF relative L2 and the binary transmittance prior; the
backscatter excess term; the DS-NeRF depth loss on sparse SfM depths."""

from __future__ import annotations

import math

from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor

from nerfstudio.cameras.rays import RaySamples
from nerfstudio.model_components.losses import DepthLossType, depth_loss


def rawnerf_loss(
    pred: Float[Tensor, "*batch 3"], target: Float[Tensor, "*batch 3"], eps: float = 1e-3
) -> Float[Tensor, ""]:
    """RawNeRF's relative L2 for linear images, ``mean(((pred - target) / (sg(pred) + eps))^2)``.

    Its gradient is that of an L2 loss on ``log(pred + eps)`` (to first order), so dark
    linear pixels count as much as bright ones (Mildenhall et al., CVPR 2022).
    """
    scale = pred.detach().clamp_min(0.0) + eps
    return torch.mean(((pred - target) / scale) ** 2)


def backscatter_excess_loss(
    backscatter: Float[Tensor, "*batch 3"], target: Float[Tensor, "*batch 3"], eps: float = 1e-3
) -> Float[Tensor, ""]:
    """``mean((max(0, B - I) / (I + eps))^2)``: the backscatter ``B`` above the image ``I``,
    relative as the RawNeRF loss.

    ``I = J e^{-beta_D r} + B`` with ``J >= 0`` puts every pixel at or above its backscatter, so the
    loss is zero at the true medium (up to noise). A medium whose backscatter alone overshoots the
    image can only be fitted with a black object colour (``J = 0``), and there the colour's sigmoid
    saturates and stops learning while the backscatter density settles on the backscatter-only fit
    (measured on the fog demo: green ``beta_B`` 1.50 /m, the backscatter-only fit of the true image,
    against 1.2). This term pushes the medium, not the colour, out of that state. Computed in
    float32; the relative excess is capped at ``1e15`` so that its square stays finite.
    """
    target = target.float()
    excess = torch.relu(backscatter.float() - target) / (target.clamp_min(0.0) + eps)
    return torch.mean(excess.clamp_max(1e15) ** 2)


def binary_transmittance_loss(
    transmittance: Float[Tensor, "*batch S 1"], scale: float = 0.1, empty_weight: float = 1.0
) -> Float[Tensor, ""]:
    """Negative log of a two-Laplacian mixture with modes at 0 and 1 (paper eq. 18).

    ``-log(e^{-|T|/scale} + w e^{-|1-T|/scale})`` with ``w = empty_weight``, averaged over
    samples; evaluated with logsumexp so it stays finite for any ``T``. Pushes the object
    transmittance to 0 or 1; ``w > 1`` prefers 1 (empty space), as the official code
    (``w = 6``): then a wall across open water, which the image alone cannot rule out, costs.
    """
    if empty_weight <= 0:
        raise ValueError(f"empty_weight must be > 0, got {empty_weight}")
    t = transmittance.float()
    logits = torch.stack([-t.abs() / scale, math.log(empty_weight) - (1.0 - t).abs() / scale], dim=0)
    return -torch.logsumexp(logits, dim=0).mean()


def depth_kernel_variance(
    starts: Float[Tensor, "*batch S 1"],
    ends: Float[Tensor, "*batch S 1"],
    termination_range: Float[Tensor, "*batch 1"],
    sigma_floor: float,
) -> Float[Tensor, "*batch 1 1"]:
    """Variance of the DS-NeRF depth kernel per ray: ``max(sigma_floor, h)^2``, where ``h`` is the
    length of the sample interval whose midpoint is nearest the known range (same units as
    ``starts``; detached).

    The DS-NeRF loss weighs ``-log w_i`` by ``exp(-(t_i - d)^2 / 2 sigma^2)`` at the sample
    midpoints ``t_i``. A kernel much narrower than the spacing falls between samples and gives
    no gradient: on the turbid demo (objects 1-8 m, samples about 0.5 m apart at 5 m before the
    proposal samplers learn) a fixed 2 cm left the geometry unformed. With ``sigma >= h`` the
    nearest midpoint gets at least ``e^{-1/8}`` of the kernel; where the samples are denser
    than ``sigma_floor`` the kernel is the floor, as before. The width is capped at the square
    root of the dtype's largest value, so the variance stays finite for any finite input.
    """
    midpoints = 0.5 * (starts + ends)
    nearest = torch.argmin((midpoints - termination_range[..., None, :]).abs(), dim=-2, keepdim=True)
    spacing = torch.gather(ends - starts, -2, nearest)
    largest = torch.finfo(spacing.dtype).max ** 0.5  # its square is still finite
    return torch.clamp(spacing.detach(), min=sigma_floor).clamp(max=largest) ** 2


def sfm_depth_loss(
    weights: Float[Tensor, "*batch S 1"],
    ray_samples: RaySamples,
    expected_depth: Float[Tensor, "*batch 1"],
    known_depth: Float[Tensor, "*batch 1"],
    directions_norm: Float[Tensor, "*batch 1"],
    sigma_floor: float,
    is_euclidean: bool = False,
    accumulation: Optional[Float[Tensor, "*batch 1"]] = None,
) -> Float[Tensor, ""]:
    """nerfstudio's DS-NeRF depth loss on the object weights, averaged over the rays whose depth is
    known (not over the batch, so its weight does not depend on how sparse the SfM points are).

    ``known_depth``: z-depth in scene units, 0 where unknown (``is_euclidean``: the range, ``inf``
    for open water, whose object opacity ``accumulation`` is then pushed to 0). The kernel's
    variance is :func:`depth_kernel_variance` with floor ``sigma_floor`` (scene units).
    """
    hit = torch.isfinite(known_depth)
    termination = torch.where(hit, known_depth, torch.zeros_like(known_depth))
    frustums = ray_samples.frustums
    ray_range = termination if is_euclidean else termination * directions_norm
    variance = depth_kernel_variance(frustums.starts, frustums.ends, ray_range, sigma_floor)
    loss = depth_loss(
        weights=weights,
        ray_samples=ray_samples,
        termination_depth=termination,
        predicted_depth=expected_depth,
        sigma=variance,  # nerfstudio's DS-NeRF loss divides by 2 * sigma: it takes the variance
        directions_norm=directions_norm,
        is_euclidean=is_euclidean,
        depth_loss_type=DepthLossType.DS_NERF,
    )
    known = (hit & (termination > 0)).float()
    loss = loss * known.numel() / torch.clamp(known.sum(), min=1.0)
    if not is_euclidean or accumulation is None:
        return loss
    open_water = (~hit).float()
    return loss + torch.sum(accumulation * open_water) / max(1.0, float(open_water.numel()))
