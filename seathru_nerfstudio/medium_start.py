"""The medium's densities where the object field enters: the backscatter's bounded by the darkest SfM
observations, the attenuation's fitted to them.

A surface at range ``z`` (world units) shows, per channel,

    I = J e^{-β_D z} + B∞ (1 - e^{-β_B z}),   J >= 0,

so no observation lies below the backscatter: ``B∞ (1 - e^{-β_B z}) <= I``, that is

    β_B <= b(I, z) = -ln(1 - I / B∞) / z      (no bound where I >= B∞).

Each SfM observation gives such a bound; the darkest surfaces at every range give the tightest.
Sea-thru (Akkaynak & Treibitz, CVPR 2019, sec. 4.3) reads the backscatter from the darkest 1% of
the pixels; here the same 1% is taken of the per-observation bounds ``b``, so that noise on a
few dark pixels does not set it.

Why this exists: the first stage learns ``B∞`` from an empty scene while the densities wait at
their start (``medium_init_optical_depth``). Where that start puts the backscatter above the
darker surfaces, the image asks for a negative object colour; the colour's sigmoid saturates at 0
within about ten steps of the object field's entry and never returns (its gradient vanishes, and
with it the attenuation's). Path-traced coastal water (``seathru-pathtrace``, β_B 0.31, 0.14,
0.08 /m) started at 0.45 /m in every channel, and the object colour was dead by step 210
(docs/history.md, 2026-11-27). The bound is applied once, at the end of the first stage, under the
veiling light learned there, and only lowers a density.

The attenuation has no such bound, and a start too high is as fatal: a surface's light
``e^{-β_D z}`` becomes too small for the colour's gradient to stand above the noise (path-traced
fog, β 0.12 /m, started at 0.51 /m; clear air at 0.45). Nor may it start far too low: surfaces then
render brighter than the image, and the object density collapses within ten steps (the formula-drawn
water demo, red started at 0.64 /m against 1.3). So the attenuation starts where the SfM
observations put it, by the medium fit (:func:`~seathru_nerfstudio.medium_fit.fit_densities`) under
the same veiling light, in each channel whose fit is certain (standard error of ``ln β_D`` at most
``research.medium_fit_max_log_error``); elsewhere at most at the backscatter's cap, the densest
uniform medium (``β_D = β_B``) the darkest surfaces allow. Nothing is held: the medium fit at
``medium_fit_step`` fits again, under the veiling light learned by then.

Units: ranges in world units, densities per world unit, colours linear.
"""

from __future__ import annotations

from typing import Any

import torch
from jaxtyping import Float
from torch import Tensor

from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio.medium_field import inverse_softplus
from seathru_nerfstudio.medium_fit import fit_densities
from seathru_nerfstudio.metadata_keys import SFM_OBSERVATIONS_KEY
from seathru_nerfstudio.phases import TrainingPhases

DENSITY_FLOOR = 1e-6
"""The cap never goes below this (per world unit): a softplus parameter cannot hold 0 exactly."""

DARK_QUANTILE = 0.01
"""Sea-thru's share of darkest pixels: the bound is this quantile of the per-observation bounds."""


def backscatter_density_bounds(
    ranges: Float[Tensor, "N"], colours: Float[Tensor, "N 3"], veil: Float[Tensor, "3"]
) -> Float[Tensor, "N 3"]:
    """Per observation and channel, the largest ``β_B`` (per world unit) that keeps the backscatter
    at or below the observed colour: ``-ln(1 - I / B∞) / z``, computed as ``-log1p(-I / B∞) / z``.
    ``inf`` where ``I >= B∞`` (any density keeps ``B∞ (1 - e^{-β_B z}) < B∞ <= I``), ``0`` where
    ``I <= 0``; ``ranges > 0``, ``veil >= 0`` (a zero veil bounds nothing: ``inf``)."""
    ratio = colours / veil.clamp_min(torch.finfo(colours.dtype).tiny)
    below = ratio < 1.0
    safe_ratio = torch.where(below, ratio.clamp_min(0.0), torch.zeros_like(ratio))  # log1p(-1) never taken
    bound = -torch.log1p(-safe_ratio) / ranges[:, None]
    return torch.where(below & (veil > 0), bound, torch.full_like(bound, float("inf")))


def backscatter_density_cap(
    ranges: Float[Tensor, "N"], colours: Float[Tensor, "N 3"], veil: Float[Tensor, "3"], quantile: float = DARK_QUANTILE
) -> Float[Tensor, "3"]:
    """The ``quantile`` of :func:`backscatter_density_bounds` per channel over the observations
    with finite positive range and finite colour (``inf`` where none, or where the quantile falls
    among the unbounded ones). Per world unit."""
    usable = torch.isfinite(ranges) & (ranges > 0) & torch.isfinite(colours).all(dim=-1)
    if not bool(usable.any()):
        return torch.full_like(veil, float("inf"))
    bounds = backscatter_density_bounds(ranges[usable], colours[usable], veil)
    return torch.quantile(bounds, quantile, dim=0, interpolation="lower")


def apply_medium_start(model: Any, step: int, optimizers: Any = None) -> None:
    """Callback at the end of the first stage: from the dataparser's SfM observations, under the
    veiling light learned so far, lower the scene medium's backscatter densities to
    :func:`backscatter_density_cap` (one below stays), and set each attenuation density to the
    medium fit's where that is certain, else to at most the same cap. ``optimizers``: the trainer's,
    whose ``medium_density`` Adam state is cleared where a density moved."""
    config = model.config
    if not TrainingPhases(config, step).ends(config.medium_first_steps) or config.medium_scope != "scene":
        return
    if config.research.medium_oracle is not None:
        return
    table = (model.kwargs.get("metadata") or {}).get(SFM_OBSERVATIONS_KEY)
    if table is None or table.num_observations == 0:
        return
    medium = model.medium_field
    with torch.no_grad():
        densities = torch.nn.functional.softplus(medium.density_raw.double()) * model.world_scale  # per world unit
        veil = torch.sigmoid(medium.rgb_logit.double())
    ranges, colours = torch.from_numpy(table.ranges), torch.from_numpy(table.colours)
    seen = torch.isfinite(ranges)
    cap = backscatter_density_cap(ranges[seen], colours[seen], veil).clamp_min(DENSITY_FLOOR)
    fit = fit_densities(ranges, colours, veil, densities[:3], densities[3:])
    certain = fit.attenuation_log_error <= config.research.medium_fit_max_log_error
    beta_d = torch.where(certain, fit.attenuation, torch.minimum(densities[:3], cap))
    beta_b = torch.minimum(densities[3:], cap)
    started = torch.cat([beta_d, beta_b])
    with torch.no_grad():
        per_scene_unit = started / model.world_scale
        medium.density_raw.copy_(torch.tensor([inverse_softplus(float(d)) for d in per_scene_unit]))
    if optimizers is not None and "medium_density" in optimizers.optimizers:
        optimizers.optimizers["medium_density"].state.clear()
    show = lambda values: ", ".join(f"{float(v):.3g}" for v in values)  # noqa: E731
    CONSOLE.print(
        f"[bold]seathru step {step}: the medium starts from {table.num_observations} SfM observations under B_inf "
        f"{show(veil)}: beta_D {show(densities[:3])} -> {show(beta_d)} /m (fitted in channel(s) "
        f"{certain.nonzero().flatten().tolist()}, standard error of ln beta_D {show(fit.attenuation_log_error)}), "
        f"beta_B {show(densities[3:])} -> {show(beta_b)} /m (capped by the darkest 1%)"
    )
