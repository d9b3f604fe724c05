"""Pure rendering maths of SeaThru-NeRF (Levy et al., CVPR 2023, secs. 3-4).

Conventions, used by every function here:

* A ray is sampled in ``S`` contiguous intervals ``[s_i, s_i + delta_i]`` (nerfstudio's
  ``frustums.starts`` and ``deltas``). ``s`` is the distance from the camera centre along
  the unit ray direction, in scene units (world units times the dataparser scale).
* Densities are per scene unit: ``sigma_obj`` per sample, shape ``[..., S, 1]``; the
  medium's ``sigma_attn`` and ``sigma_bs`` are constant along a ray, shape ``[..., 3]``.
* Colours are linear radiance; nothing here clamps or applies a gamma.
* Inside an interval the object's and the medium's densities are constant.

Two quadratures of the final model (sec. 4.3) are offered:

``"paper"``
    The paper's equations as printed:
    ``direct_i = T_i e^{-sigma_attn s_i} (1 - e^{-sigma_obj,i delta_i}) c_obj,i`` and
    ``backscatter_i = T_i e^{-sigma_bs s_i} (1 - e^{-sigma_bs delta_i}) c_med``.
    In the interval that holds a surface the medium is counted as if the surface were
    not there, so an opaque wall at ``z`` shows backscatter up to ``z + delta``.

``"analytic"`` (default)
    The exact integral of the same piecewise-constant ray, where object and medium
    compete inside an interval:
    ``direct_i = T_i e^{-sigma_attn s_i} sigma_obj/(sigma_obj + sigma_attn)
    (1 - e^{-(sigma_obj + sigma_attn) delta_i}) c_obj,i`` and likewise for the
    backscatter with ``sigma_bs``. It equals ``"paper"`` wherever ``sigma_obj = 0``
    and reduces *exactly* to the SeaThru image formation model
    ``I = J e^{-beta_D z} + B_inf (1 - e^{-beta_B z})`` for an opaque surface at
    range ``z``, wherever the surface falls.

Beyond the paper (which truncates the ray at the far plane), the backscatter also holds
the closed-form medium before the first sample, ``(1 - e^{-sigma_bs s_0}) c_med``, and
after the last one, ``T_N e^{-sigma_bs s_N} c_med``: the water starts at the camera and
goes on to infinity, so a ray that hits nothing shows the veiling light ``c_med`` and the
near/far planes no longer clip the medium. (In clear air, ``sigma_bs = 0`` exactly, there is
no backscatter at all.)

Light falls from above, so the water higher up is brighter. Along a ray with ``sin`` of elevation
``u`` the light the medium scatters grows as ``e^{kappa u t}`` (``kappa``: the light's attenuation
with depth, per scene unit), and the backscatter in front of a surface at range ``z`` is

    B∞ sigma_bs / a (1 - e^{-a z}),   a = sigma_bs - kappa u:

the backscatter of a homogeneous medium whose veil is ``B∞ G``, ``G = sigma_bs / a``, and whose
backscatter density is ``sigma_bs / G``. Its rate at the camera, ``B∞ sigma_bs``, is the same in
every direction; only the veil, the far water, brightens looking up (:func:`depth_lit_backscatter_density`).

The open water can be brighter than the veil the surfaces fade to (:mod:`seathru_nerfstudio.surface_veil`): with
``surface_veil = r`` (per channel, ``<= 1``) a surface is seen through ``r B∞ (1 - e^{-sigma_bs z})``, and the open
water's excess ``(1 - r) B∞`` reaches a ray only past all matter, weighted by ``e^{-tau_N}``.

All maths runs in float32 with autocast disabled, so fp16/bf16 inputs give finite outputs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor

Quadrature = Literal["analytic", "paper"]

SIGMA_MAX = 1e18
"""Densities are clamped to this, so sums and products of them stay finite in float32."""

_SERIES_BELOW = 1e-3
"""Below this optical depth, ``(1 - e^{-x}) / x`` is evaluated from its Taylor series."""


def one_minus_exp(x: Tensor) -> Tensor:
    """``1 - e^{-x}`` without cancellation for small ``x``."""
    return -torch.expm1(-x)


def exclusive_optical_depth(
    densities: Float[Tensor, "*batch S 1"], deltas: Float[Tensor, "*batch S 1"]
) -> Float[Tensor, "*batch S+1 1"]:
    """Object optical depth ``tau_i = sum_{j<i} sigma_j delta_j`` at every interval start
    and, as the last entry, at the end of the last interval."""
    zeros = torch.zeros_like(densities[..., :1, :])
    return torch.cat([zeros, torch.cumsum(densities * deltas, dim=-2)], dim=-2)


def object_weights(
    object_density: Float[Tensor, "*batch S 1"], deltas: Float[Tensor, "*batch S 1"]
) -> tuple[Float[Tensor, "*batch S 1"], Float[Tensor, "*batch S 1"], Float[Tensor, "*batch S+1 1"]]:
    """The object alone, without the medium: weights ``w_i = T_i (1 - e^{-sigma_obj,i delta_i})``,
    transmittance ``T_i = e^{-tau_i}`` at each interval start, and the optical depths ``tau_i``
    (:func:`exclusive_optical_depth`, the last one at the end of the ray). Densities are clamped to ``[0, SIGMA_MAX]`` and deltas to ``>= 0``;
    float32 (float64 for float64 inputs) with autocast disabled, so any finite input gives
    finite outputs."""
    dtype = torch.promote_types(object_density.dtype, torch.float32)
    with torch.autocast(device_type=object_density.device.type, enabled=False):
        sigma_obj = object_density.to(dtype).clamp(0.0, SIGMA_MAX)
        delta = deltas.to(dtype).clamp_min(0.0)
        tau = exclusive_optical_depth(sigma_obj, delta)  # [..., S+1, 1]
        transmittance = torch.exp(-tau[..., :-1, :])
        return transmittance * one_minus_exp(sigma_obj * delta), transmittance, tau


def depth_lit_backscatter_density(
    sigma_bs: Float[Tensor, "*batch 3"], veil_gain: Float[Tensor, "*batch 3"]
) -> Float[Tensor, "*batch 3"]:
    """``sigma_bs / G``: the backscatter density, per scene unit, of a ray whose veil is ``G >= 1``
    times the level veil ``B∞`` because the light grows along it (module docstring), so that
    ``B∞ G (1 - e^{-sigma_bs z / G})`` keeps the slope ``B∞ sigma_bs`` at ``z = 0``. ``G`` is
    clamped to ``>= 1`` (a veil that rises, never one that falls) and ``<= 1 / tiny``."""
    gain = veil_gain.to(sigma_bs.dtype).clamp(1.0, 1.0 / torch.finfo(torch.float32).tiny)
    return sigma_bs / gain


def absorbed_fraction(
    sigma_part: Tensor, sigma_total: Tensor, delta: Tensor
) -> Tensor:
    """``int_0^delta sigma_part e^{-sigma_total t} dt
    = sigma_part / sigma_total * (1 - e^{-sigma_total delta})``.

    The share of an interval's light that one of two competing densities takes. Needs
    ``0 <= sigma_part <= sigma_total``; finite with finite gradients from ``sigma_total
    delta = 0`` (where it is ``sigma_part delta``) to ``sigma_total delta -> inf`` (where it
    is ``sigma_part / sigma_total``). Never divides by zero, never forms ``0 * inf``.
    """
    x = sigma_total * delta
    large = x > _SERIES_BELOW
    # Each branch only sees inputs for which it is finite, so torch.where's unused branch
    # cannot leak NaN into the gradient.
    safe_total = torch.where(large, sigma_total, torch.ones_like(sigma_total))
    x_small = torch.where(large, torch.zeros_like(x), x)
    delta_small = torch.where(large, torch.zeros_like(delta), delta)
    exact = sigma_part / safe_total * one_minus_exp(torch.where(large, x, torch.ones_like(x)))
    series = sigma_part * delta_small * (1.0 - x_small / 2.0 + x_small * x_small / 6.0)
    return torch.where(large, exact, series)


@dataclass
class SeathruRender:
    """What one call of :func:`render_seathru` returns (all linear, per ray)."""

    rgb: Float[Tensor, "*batch 3"]
    """Image in the medium: ``direct + backscatter``."""
    direct: Float[Tensor, "*batch 3"]
    """Object light that reaches the camera, attenuated by the medium."""
    backscatter: Float[Tensor, "*batch 3"]
    """Light scattered toward the camera by the medium, camera to infinity."""
    clean: Float[Tensor, "*batch 3"]
    """The object as in clear air, ``sum_i w_i c_obj,i`` (black where nothing is hit)."""
    weights: Float[Tensor, "*batch S 1"]
    """Object weights ``w_i = T_i (1 - e^{-sigma_obj,i delta_i})`` (no medium in them)."""
    transmittance: Float[Tensor, "*batch S 1"]
    """Object transmittance ``T_obj,i`` at each interval start."""
    accumulation: Float[Tensor, "*batch 1"]
    """Object opacity of the ray, ``sum_i w_i = 1 - T_obj,N``."""


def render_seathru(
    object_rgb: Float[Tensor, "*batch S 3"],
    object_density: Float[Tensor, "*batch S 1"],
    starts: Float[Tensor, "*batch S 1"],
    deltas: Float[Tensor, "*batch S 1"],
    medium_rgb: Float[Tensor, "*batch 3"],
    sigma_attn: Float[Tensor, "*batch 3"],
    sigma_bs: Float[Tensor, "*batch 3"],
    quadrature: Quadrature = "analytic",
    veil_from_open_rays: bool = False,
    veil_gain: Float[Tensor, "*batch 3"] | None = None,
    surface_veil: Float[Tensor, "*batch 3"] | None = None,
) -> SeathruRender:
    """Render rays through an object field in a per-ray homogeneous medium (sec. 4.3).

    The basic model of sec. 4.1 (eqs. 11-13, one medium density) is this function with
    ``sigma_attn = sigma_bs`` and ``quadrature="paper"``.

    ``veil_from_open_rays``: the same values, but the gradient reaching ``medium_rgb`` is scaled,
    ray by ray, by the share of the ray that passes all matter, ``T_obj,N = e^{-tau_N}``. The
    veiling light is the colour at infinity, seen directly only where the view is open; on a ray
    that ends on a surface, ``B_inf`` and ``sigma_bs`` trade off along ``B_inf (1 - e^{-sigma_bs z})``,
    and this leaves that trade to the densities.

    ``veil_gain`` (``G >= 1``, per ray and channel): ``medium_rgb`` is the level veil times ``G``, the
    far water brighter looking up; the backscatter density is then ``sigma_bs / G``
    (:func:`depth_lit_backscatter_density`), so only the far water brightens. ``None``: ``G = 1``.

    ``surface_veil`` (``r`` in ``[0, 1]``, per ray and channel): the veil in front of the surfaces is
    ``r c_med``, and the rest of the open water's veil, ``(1 - r) c_med``, reaches a ray only past all
    matter: ``backscatter = c_med (r (1 - e^{-sigma_bs t}) + (1 - r) e^{-tau_N})`` in the closed form, so an
    open ray shows ``c_med`` and one that ends on an opaque surface at ``z`` shows
    ``r c_med (1 - e^{-sigma_bs z})`` (:mod:`seathru_nerfstudio.surface_veil`). ``None``: ``r = 1``.
    """
    if quadrature not in ("analytic", "paper"):
        raise ValueError(f"unknown quadrature {quadrature!r}; expected 'analytic' or 'paper'")
    dtype = torch.promote_types(object_rgb.dtype, torch.float32)  # float32, or float64 for float64 inputs
    with torch.autocast(device_type=object_rgb.device.type, enabled=False):
        c_obj = object_rgb.to(dtype)
        sigma_obj = object_density.to(dtype).clamp(0.0, SIGMA_MAX)
        s = starts.to(dtype).clamp_min(0.0)
        delta = deltas.to(dtype).clamp_min(0.0)
        c_med = medium_rgb.to(dtype)[..., None, :]  # [..., 1, 3]
        attn = sigma_attn.to(dtype).clamp(0.0, SIGMA_MAX)[..., None, :]
        bs = sigma_bs.to(dtype).clamp(0.0, SIGMA_MAX)
        if veil_gain is not None:
            bs = depth_lit_backscatter_density(bs, veil_gain.to(dtype))
        bs = bs[..., None, :]

        weights, transmittance, tau = object_weights(sigma_obj, delta)  # tau: [..., S+1, 1]
        tau_start, tau_end = tau[..., :-1, :], tau[..., -1:, :]

        # Object transmittance and medium attenuation combined in log space: one exp.
        reach_direct = torch.exp(-(tau_start + attn * s))  # [..., S, 3]
        reach_bs = torch.exp(-(tau_start + bs * s))
        if quadrature == "analytic":
            direct_share = absorbed_fraction(sigma_obj, sigma_obj + attn, delta)
            bs_share = absorbed_fraction(bs, sigma_obj + bs, delta)
        else:
            direct_share = one_minus_exp(sigma_obj * delta)
            bs_share = one_minus_exp(bs * delta)
        direct = torch.sum(reach_direct * direct_share * c_obj, dim=-2)
        inside = torch.sum(reach_bs * bs_share, dim=-2)

        s_first = s[..., 0, :]  # [..., 1]
        s_last = s[..., -1, :] + delta[..., -1, :]
        head = one_minus_exp(bs[..., 0, :] * s_first)
        # int_{s_N}^inf sigma e^{-sigma t} dt is e^{-sigma s_N} for any sigma > 0, but 0 in
        # clear air (sigma = 0): an infinite medium veils fully however thin it is.
        tail = torch.where(
            bs[..., 0, :] > 0,
            torch.exp(-(tau_end[..., 0, :] + bs[..., 0, :] * s_last)),
            torch.zeros_like(bs[..., 0, :]),
        )
        veil = c_med[..., 0, :]
        if veil_from_open_rays:
            open_share = torch.exp(-tau_end[..., 0, :]).detach()  # [..., 1]
            veil = veil * open_share + veil.detach() * (1.0 - open_share)
        medium_share = head + inside + tail
        if surface_veil is not None:
            share = surface_veil.to(dtype).clamp(0.0, 1.0)
            medium_share = share * medium_share + (1.0 - share) * torch.exp(-tau_end[..., 0, :])
        backscatter = medium_share * veil

        clean = torch.sum(weights * c_obj, dim=-2)
        accumulation = one_minus_exp(tau_end[..., 0, :])

    return SeathruRender(
        rgb=direct + backscatter,
        direct=direct,
        backscatter=backscatter,
        clean=clean,
        weights=weights,
        transmittance=transmittance,
        accumulation=accumulation,
    )


def formation_model(
    clean: Float[Tensor, "*batch 3"],
    depth: Float[Tensor, "*batch 1"],
    beta_d: Float[Tensor, "*batch 3"],
    beta_b: Float[Tensor, "*batch 3"],
    veiling_light: Float[Tensor, "*batch 3"],
) -> Float[Tensor, "*batch 3"]:
    """SeaThru image formation ``I = J e^{-beta_D z} + B_inf (1 - e^{-beta_B z})``.

    ``z`` is the range from the camera centre, in the units the betas are per; ``z = inf``
    (open water) gives ``B_inf``. Linear radiance in, linear radiance out.
    """
    finite = torch.isfinite(depth)
    z = torch.where(finite, depth, torch.zeros_like(depth))
    direct = torch.where(finite, clean * torch.exp(-beta_d * z), torch.zeros_like(clean))
    veil = torch.where(finite, one_minus_exp(beta_b * z), torch.ones_like(clean))
    return direct + veiling_light * veil
