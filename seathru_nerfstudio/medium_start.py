"""The backscatter density where the object field enters, bounded by the darkest SfM observations.

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

The attenuation keeps its start: nothing bounds it from the darkest pixels, and a start too low
is as harmful as one too high (surfaces rendered brighter than the image lose their density at
entry). A start from the medium fit under the first stage's veil was measured and reverted
(docs/history.md, 2026-11-27: on a short first stage the veil has not settled and the fit is wrong).

Units: ranges in world units, densities per world unit, colours linear.
"""

from __future__ import annotations

from typing import Any

import torch
from jaxtyping import Float
from torch import Tensor

from nerfstudio.utils.rich_utils import CONSOLE

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


def apply_backscatter_cap(model: Any, step: int, optimizers: Any = None) -> None:
    """Callback at the end of the first stage: lower the scene medium's backscatter densities to
    :func:`backscatter_density_cap` of the dataparser's SfM observations under the veiling light
    learned so far; a density already below stays. ``optimizers``: the trainer's, whose
    ``medium_density`` Adam state is cleared where a density moved."""
    config = model.config
    if not TrainingPhases(config, step).ends(config.medium_first_steps) or config.medium_scope != "scene":
        return
    if config.research.medium_oracle is not None or config.medium_model == "none":
        return  # an oracle is the medium; clear air renders none
    table = (model.kwargs.get("metadata") or {}).get(SFM_OBSERVATIONS_KEY)
    if table is None or table.num_observations == 0:
        return
    medium = model.medium_field
    with torch.no_grad():
        densities = torch.nn.functional.softplus(medium.density_raw.double()) * model.world_scale  # per world unit
        veil = torch.sigmoid(medium.rgb_logit.double())
    seen = torch.isfinite(torch.from_numpy(table.ranges))
    cap = backscatter_density_cap(torch.from_numpy(table.ranges)[seen], torch.from_numpy(table.colours)[seen], veil)
    beta_b = torch.minimum(densities[3:], cap.clamp_min(DENSITY_FLOOR))
    if bool((beta_b >= densities[3:]).all()):
        return
    medium.set_densities(beta_b / model.world_scale, first=3)
    if optimizers is not None and "medium_density" in optimizers.optimizers:
        optimizers.optimizers["medium_density"].state.clear()
    show = lambda values: ", ".join(f"{float(v):.3g}" for v in values)  # noqa: E731
    CONSOLE.print(
        f"[bold]seathru step {step}: backscatter density capped by the darkest 1% of {table.num_observations} SfM "
        f"observations under B_inf {show(veil)}: beta_B {show(densities[3:])} -> {show(beta_b)} /m"
    )
