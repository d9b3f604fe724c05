"""When the medium's densities are fitted in training, and the veil in front of the surfaces read.

At ``medium_fit_step`` (500) the densities are fitted to the SfM points' colours across views
(:func:`~seathru_nerfstudio.medium_fit.fit_densities`) under the veiling light held since the first stage,
then, where the surfaces the water has put out show a darker veil (:mod:`seathru_nerfstudio.surface_veil`),
fitted again under that veil, and held from then on, moving from the trained values to the fit over
``research.auto_blend_steps``.

The veil in front of the surfaces can only be read from surfaces the object field has already placed deep in
the water, and at step 500 it often has not: on path-traced coastal water three of six runs found under 1% of
their surface rays three attenuation lengths away (coastal 3 seed 42: 0.29%, coastal 4: 0.14% and 0%), where
the true ranges put 8-9% of the object pixels (docs/history.md, 2026-12-07). SfM, which the geometry follows
then, triangulated under 2% of its points past 10 m. Such a channel is read once more, from the surface rays
of a window as long as the first that starts when the move to the fit has ended (steps 700-850 by default),
when the object field has had the images alone to place the far surfaces; where it now reads, the densities
are fitted again under the new veil and move there as they did after the fit.
"""

from __future__ import annotations

from typing import Any

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio.medium_fit import (
    DensityFit,
    fit_densities,
    fit_model_medium,
    fit_replaces,
    sfm_observation_table,
    veil_sensitivity,
)
from seathru_nerfstudio.oracles import replace_with_truth
from seathru_nerfstudio.phases import TrainingPhases
from seathru_nerfstudio.surface_veil import read_surface_veil


def _show(values: Tensor) -> str:
    return ", ".join(f"{float(v):.3g}" for v in values)


def _refit(model: Any, table: Any, veil: Float[Tensor, "3"], start: Float[Tensor, "6"]) -> DensityFit:
    """:func:`fit_densities` on ``table`` under ``veil``, started at ``start`` (``β_D`` then ``β_B``, 1/world
    unit), tied as the medium model in use."""
    return fit_densities(
        torch.from_numpy(table.ranges), torch.from_numpy(table.colours), veil, start[:3], start[3:], tie=model.medium_model
    )


def _record_errors(model: Any, table: Any, veil: Float[Tensor, "3"], fit: DensityFit) -> None:
    """Keep the fit's standard errors and ``β_B``'s sensitivity to the veil on the model (``medium.json``)."""
    model.fit_log_error.copy_(fit.attenuation_log_error.to(model.fit_log_error))
    model.fit_backscatter_log_error.copy_(fit.backscatter_log_error.to(model.fit_backscatter_log_error))
    sensitivity = veil_sensitivity(torch.from_numpy(table.ranges), torch.from_numpy(table.colours), veil, fit, model.medium_model)
    model.backscatter_veil_sensitivity.copy_(
        torch.nan_to_num(sensitivity, nan=0.0, posinf=0.0, neginf=0.0).to(model.backscatter_veil_sensitivity)
    )


def _held_densities(
    model: Any, fit: DensityFit, densities: Float[Tensor, "6"], held_before: Bool[Tensor, "6"], step: int
) -> tuple[Float[Tensor, "6"], Bool[Tensor, "6"]]:
    """The densities to hold (1/world unit, ``β_D`` then ``β_B``) and which of the six are held: the fit's
    where it replaces (:func:`~seathru_nerfstudio.medium_fit.fit_replaces`), else ``densities``; held
    where the fit replaces or ``held_before``. With ``research.medium_fit_oracle`` the truth."""
    uncertain = ~fit_replaces(fit, model.config.research.medium_fit_max_log_error)
    beta_d = torch.where(uncertain, densities[:3], fit.attenuation)
    beta_b = torch.where(uncertain, densities[3:], fit.backscatter)
    replaced = torch.cat([~uncertain, ~uncertain])
    if model.fit_oracle is not None:  # diagnostic: the truth in place of the fit, held like it
        parts = model.config.research.medium_fit_oracle_parts
        beta_d, beta_b, replaced = replace_with_truth(model.fit_oracle, parts, beta_d, beta_b, ~uncertain)
        CONSOLE.print(f"[bold]seathru step {step}: medium_fit_oracle: the true densities ({parts}) replace the fit")
    return torch.cat([beta_d, beta_b]), replaced | held_before.to(replaced.device)


def _move_held(model: Any, step: int) -> None:
    """Move the held densities (and the surfaces' veil) towards their targets over ``research.auto_blend_steps``
    after the fit and after the second reading of the veil; a move whose ends are equal changes nothing."""
    config = model.config
    blend = max(config.research.auto_blend_steps, 1)
    windows = TrainingPhases(config, step).surface_veil_windows
    starts = [config.medium_fit_step or 0] + ([windows[1][1]] if len(windows) > 1 else [])
    for start in starts:
        after = step - start + 1  # 0 at the step the move was set (its last: 499, 849)
        if 0 < after <= config.research.auto_blend_steps:
            model.medium_field.move_to_fit(after / blend, model.densities_fitted.cpu())


def apply_medium_fit(model: Any, step: int, optimizers: Any = None) -> None:
    """The ``medium_fit_step`` callback: replace the scene medium's densities by
    :func:`~seathru_nerfstudio.medium_fit.fit_densities` on the dataparser's SfM observation table, under the
    veiling light learned so far, tied as the medium model in use renders them, and hold them from then on
    (``model.densities_fitted``), moving from the trained values to the fit in log space over
    ``research.auto_blend_steps`` (:meth:`~seathru_nerfstudio.medium_field.SceneMedium.move_to_fit`).
    Set at once, the fit's change of the image emptied the object field within 15 steps on
    path-traced coastal water (opacity 0.65 → 0.14–0.19 on three runs of seed 42, depth error 0.1 →
    0.9–1.5; 0.63 with the move; docs/history.md, 2026-11-29). A channel the fit is uncertain about
    (standard error of ``ln β_D`` above ``research.medium_fit_max_log_error``;
    :func:`~seathru_nerfstudio.medium_fit.fit_replaces`) keeps its trained densities and trains on.
    At the end of the second window of the surfaces' veil, :func:`reread_surface_veil`.
    ``optimizers``: the trainer's, whose ``medium_density`` Adam state is cleared."""
    config = model.config
    if model.fits_medium:
        _move_held(model, step)
    phases = TrainingPhases(config, step)
    if model.fits_medium and phases.rereads_surface_veil:
        reread_surface_veil(model, step)
        return
    if not (model.fits_medium and phases.ends(config.medium_fit_step)):
        return
    table = sfm_observation_table(model)
    if table is None:
        CONSOLE.print(
            f"[bold yellow]seathru step {step}: no SfM observations to fit the medium to (no SfM depth maps or "
            "COLMAP tracks); the densities train on"
        )
        return
    if model.medium_model == "none":
        CONSOLE.print(f"[bold]seathru step {step}: no medium to fit (medium model none)")
        return
    medium = model.medium_field
    densities, veil, fit = fit_model_medium(model, table, tie=model.medium_model)
    surface_veil = read_surface_veil(model, fit.attenuation, step)
    if surface_veil is not None:  # the fit again, under the veil in front of the surfaces
        veil = veil * surface_veil
        fit = _refit(model, table, veil, torch.cat([fit.attenuation, fit.backscatter]))
    _record_errors(model, table, veil, fit)
    uncertain = ~fit_replaces(fit, config.research.medium_fit_max_log_error)
    if uncertain.all() and model.fit_oracle is None:  # nothing to replace: leave the parameters and Adam alone
        CONSOLE.print(
            f"[bold]seathru step {step}: medium fit to {table.num_observations} SfM observations kept the trained "
            f"densities: the fit is imprecise (standard error of ln beta_D {_show(fit.attenuation_log_error)} above "
            f"{config.research.medium_fit_max_log_error:g}; fitted beta_D {_show(fit.attenuation)} /m)"
        )
        return
    held, replaced = _held_densities(model, fit, densities, torch.zeros(6, dtype=torch.bool), step)
    medium.start_move_to_fit(held / model.world_scale, surface_veil)  # reached after auto_blend_steps
    if optimizers is not None and "medium_density" in optimizers.optimizers:
        optimizers.optimizers["medium_density"].state.clear()  # Adam's moments were for the old values
    model.densities_fitted.copy_(replaced.to(model.densities_fitted.device))
    CONSOLE.print(
        f"[bold]seathru step {step}: medium fitted to {table.num_observations} SfM observations ({model.medium_model} tie)[/] "
        f"(residual {fit.residual:.3g}): beta_D {_show(densities[:3])} -> {_show(held[:3])} /m, "
        f"beta_B {_show(densities[3:])} -> {_show(held[3:])} /m, under B_inf {_show(veil)}; "
        f"standard error of ln beta_D {_show(fit.attenuation_log_error)}, of ln beta_B {_show(fit.backscatter_log_error)}; "
        f"beta_B moves {_show(model.backscatter_veil_sensitivity)} times any relative error of B_inf"
        + (f", kept the trained values of channel(s) {uncertain.nonzero().flatten().tolist()}" if uncertain.any() else "")
    )


def reread_surface_veil(model: Any, step: int) -> None:
    """Read the veil in front of the surfaces again for the channels still at one veil (module docstring), from
    the surface rays of the second window, under the held attenuation; where one now reads under 1, fit the
    densities again under the new veil and move the held ones (and the veil) there over
    ``research.auto_blend_steps``. Where nothing changes, the move's ends are set equal, so it holds still."""
    medium = model.medium_field
    table = sfm_observation_table(model)
    if table is None or model.medium_model == "none" or not hasattr(medium, "surface_veil"):
        return
    if not bool(model.densities_fitted.any()):  # the fit kept the trained densities: nothing is held
        return
    with torch.no_grad():
        densities = torch.nn.functional.softplus(medium.density_raw.double()).cpu() * model.world_scale
        open_water = torch.sigmoid(medium.rgb_logit.double()).cpu()
    read_before = medium.surface_veil.detach().double().cpu()
    surface_veil = read_surface_veil(model, densities[:3], step, read=read_before)
    if surface_veil is None or torch.equal(surface_veil, read_before):
        medium.start_move_to_fit(densities / model.world_scale, None)  # the ends equal: the move holds still
        return
    veil = open_water * surface_veil
    held_before = model.densities_fitted.cpu().bool()
    fit = _refit(model, table, veil, densities)
    _record_errors(model, table, veil, fit)
    held, replaced = _held_densities(model, fit, densities, held_before, step)
    medium.start_move_to_fit(held / model.world_scale, surface_veil)
    model.densities_fitted.copy_(replaced.to(model.densities_fitted.device))
    CONSOLE.print(
        f"[bold]seathru step {step}: medium fitted again to {table.num_observations} SfM observations under the veil "
        f"read again[/] (residual {fit.residual:.3g}): beta_D {_show(densities[:3])} -> {_show(held[:3])} /m, "
        f"beta_B {_show(densities[3:])} -> {_show(held[3:])} /m, under B_inf {_show(veil)}"
    )
