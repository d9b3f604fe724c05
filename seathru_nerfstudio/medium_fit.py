"""The medium's densities fitted to the SfM points' colours across views, given the veiling light.

Each observation ``k`` of point ``p`` at range ``z_k`` (world units) obeys, per channel,

    I_k = J_p a_k + B∞ (1 - e^{-β_B z_k}),   a_k = e^{-β_D z_k},

with one unknown colour ``J_p ≥ 0`` per point. For given densities the best ``J_p`` is the
least-squares ``max(0, Σ a_k (I_k - B_k) / Σ a_k²)``, so only ``β_D`` and ``β_B`` remain: they
minimise the mean squared residual. ``B∞`` must be given: the points alone hardly tell it from
the backscatter density, but the open water shows it directly (the first stage learns it).

Why this exists: the images determine ``β_D`` only through how a point's colour changes with
its range, and gradient descent on the radiance field follows that weak signal slowly (water:
22–33% high after 1500 steps on 2026-11-25; docs/history.md). Here the same information is
fitted directly, on a few thousand numbers (L-BFGS, a second or two). The fit is only as good as the veiling light given
to it; channels whose backscatter is tiny (small ``B∞``) leave ``β_B`` undetermined.

A medium model that renders tied densities (``fog``: one per kind; ``uniform``: one per channel) is
fitted tied (``tie``): the mean of free densities is not the best tied one (fog demo, all six tied:
1.03 against 1.11 /m, truth 1.2).

Some observations break the model: a point on a silhouette against open water is sampled
(bilinearly, and with SfM's position error) partly from the water behind it, in some views and not
others. Least squares lets those few pull the densities (water demo, with the true veiling light:
red β_B +21%; turbid: green β_D −37%, β_B −31%). The fit is therefore robust: iteratively reweighted
least squares with Cauchy weights (:func:`cauchy_weights`), which bring both demos within 11%
(01224da, 2026-11-26; docs/history.md, *The medium fitted to the SfM points*).

Where a channel's ``β_D`` and ``β_B`` trade off along a valley of the residual, the fit lands
anywhere on it, so each fitted log-density comes with a Gauss–Newton standard error (see
:func:`log_density_errors`); a caller keeps its own value where that error is large.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio.medium_field import tie_matrix
from seathru_nerfstudio.medium_fit_errors import LOG_DENSITY_LIMIT, log_density_errors, tied_log_density_errors
from seathru_nerfstudio.metadata_keys import SFM_OBSERVATIONS_KEY
from seathru_nerfstudio.oracles import replace_with_truth
from seathru_nerfstudio.phases import TrainingPhases
from seathru_nerfstudio.surface_veil import read_surface_veil


CAUCHY_TUNING = 2.385
"""Cauchy weights ``1 / (1 + (r / (c s))²)`` with this ``c``: 95% efficiency on Gaussian residuals
(Holland & Welsch 1977), the usual choice, not fitted to our scenes."""

MAD_TO_SIGMA = 1.4826
"""A Gaussian's standard deviation over its median absolute deviation."""


def cauchy_weights(residual_norms: Float[Tensor, "P V"], observed: Float[Tensor, "P V"]) -> Float[Tensor, "P V"]:
    """IRLS weights of the observations (0 where not observed): ``1 / (1 + (r / (c s))²)``, with
    ``r`` an observation's residual (the norm over RGB), ``c`` :data:`CAUCHY_TUNING` and ``s`` the
    robust scale ``1.4826 × median r`` over the observations. A residual of ``c s`` weighs ½, one of
    ``10 c s`` about 1%. Exact data (``s = 0``): the exact observations weigh 1, any other ~0."""
    seen = observed > 0
    scale = MAD_TO_SIGMA * residual_norms[seen].median() if bool(seen.any()) else residual_norms.new_zeros(())
    # s = 0 is floored, not divided by (no 0/0); a huge ratio weighs 0 (1 / inf), never NaN
    ratio = residual_norms / torch.clamp(CAUCHY_TUNING * scale, min=1e-30)
    return torch.where(seen, 1.0 / (1.0 + ratio**2), torch.zeros_like(residual_norms))


def best_colours(
    ranges: Float[Tensor, "P V"],
    colours: Float[Tensor, "P V 3"],
    observed: Float[Tensor, "P V"],
    beta_d: Float[Tensor, "3"],
    beta_b: Float[Tensor, "3"],
    veil: Float[Tensor, "3"],
) -> tuple[Float[Tensor, "P 3"], Float[Tensor, "P V 3"]]:
    """Per point the least-squares object colour ``J ≥ 0``, and the predicted colours.

    ``observed`` is 1 where an observation exists and 0 elsewhere (``ranges`` and ``colours``
    must be finite there too); values between weigh an observation (weighted least squares).
    Returns ``(J, J a + B)``."""
    z = ranges[..., None]
    transmittance = torch.exp(-beta_d * z)
    backscatter = veil * -torch.expm1(-beta_b * z)
    weight = observed[..., None]
    numerator = (weight * transmittance * (colours - backscatter)).sum(dim=1)
    denominator = (weight * transmittance**2).sum(dim=1)
    object_colour = torch.clamp(numerator / torch.clamp(denominator, min=1e-30), min=0.0)
    return object_colour, object_colour[:, None, :] * transmittance + backscatter


class DensityFit(NamedTuple):
    """The fitted densities (1/world unit), the mean squared residual, and the standard errors of
    ``ln β_D`` and ``ln β_B`` per channel (≈ relative errors; at most ``2 × LOG_DENSITY_LIMIT``)."""

    attenuation: Float[Tensor, "3"]
    backscatter: Float[Tensor, "3"]
    residual: float
    attenuation_log_error: Float[Tensor, "3"]
    backscatter_log_error: Float[Tensor, "3"]


NEWTON_STEP_LIMIT = 1e-12
"""The Newton polish (:func:`newton_polished`) stops once a step moves no log-density by more."""


def newton_polished(loss_of: Callable[[Tensor], Tensor], start: Float[Tensor, "K"], max_steps: int = 30) -> Float[Tensor, "K"]:
    """``start`` moved by Newton steps to the minimum of ``loss_of`` near it, to floating-point precision.

    L-BFGS stops on absolute tolerances (a change of the loss, or a slope ``g·d``, below 1e-15):
    on a mean squared residual of ~1e-4 it stops where the last bits of its sums decide, so the
    same data in another order (or another machine's reductions) ended 0.3% apart in ``β_D`` and
    8.5% apart in its standard error. Newton's method on the few log-densities converges
    quadratically from there: each step solves ``H δ = -g`` within the directions of positive
    curvature (eigenvalues of ``H`` above ``1e-10 × max``; a flat direction, which the data leave
    undetermined, stays where it is), halved until the loss does not rise by more than its
    rounding (``1e-12`` relative, at most 30 halvings). It stops once a step moves no value by
    more than :data:`NEWTON_STEP_LIMIT`, or where the curvature or the loss is not finite."""
    x = start.detach().clone()
    for _ in range(max_steps):
        at = x.clone().requires_grad_(True)
        loss = loss_of(at)
        if not loss.requires_grad:
            break  # the loss does not depend on x
        (gradient,) = torch.autograd.grad(loss, at, create_graph=True)
        if not gradient.requires_grad:
            break  # linear in x: no curvature to step by
        rows = [torch.autograd.grad(gradient[k], at, retain_graph=True, allow_unused=True)[0] for k in range(x.numel())]
        hessian = torch.stack([torch.zeros_like(x) if row is None else row for row in rows]).detach()
        hessian = (hessian + hessian.T) / 2
        gradient, loss = gradient.detach(), loss.detach()
        if not (torch.isfinite(hessian).all() and torch.isfinite(gradient).all() and torch.isfinite(loss)):
            break
        curvature, directions = torch.linalg.eigh(hessian)
        curved = curvature > 1e-10 * curvature.abs().max()
        if not bool(curved.any()):
            break
        along = directions.T @ gradient
        step = -directions @ torch.where(curved, along / torch.where(curved, curvature, 1.0), 0.0)
        for _ in range(30):
            with torch.no_grad():
                trial = loss_of(x + step)
            if torch.isfinite(trial) and trial <= loss + 1e-12 * loss.abs():
                break
            step = step / 2
        else:
            break  # no step lowers the loss: x is the minimum to rounding
        x = x + step
        if float(step.abs().max()) <= NEWTON_STEP_LIMIT:
            break
    return x


def fit_densities(
    ranges: Float[Tensor, "P V"],
    colours: Float[Tensor, "P V 3"],
    veil: Float[Tensor, "3"],
    start_attenuation: Float[Tensor, "3"],
    start_backscatter: Float[Tensor, "3"],
    max_iterations: int = 200,
    tie: str = "seathru",
    reweightings: int = 3,
) -> DensityFit:
    """``β_D, β_B`` in 1/world unit, fitted by L-BFGS on the log-densities and polished by Newton
    steps (:func:`newton_polished`: the same data in any order give the same fit), with the mean squared
    residual and the standard errors of the log-densities (:func:`log_density_errors`;
    :func:`tied_log_density_errors` under a ``tie``, the medium model whose tied densities are
    fitted as one (:func:`~seathru_nerfstudio.medium_field.tie_matrix`); its free densities start
    at the geometric mean of their starts).

    ``ranges`` and ``colours`` carry NaN where a point was not observed. The starts must be
    positive; the fit moves them in log space, so the densities stay positive (and within
    :data:`LOG_DENSITY_LIMIT`).

    ``reweightings``: after the least-squares fit, this many rounds of :func:`cauchy_weights` from
    the last fit's residuals, each refitted from where the last ended (0: least squares only; the
    demos settle after one or two). The residual and the standard errors are those of the last
    weighted fit: the down-weighted observations count by their weight."""
    if reweightings < 0:
        raise ValueError(f"fit_densities: reweightings must be >= 0 (got {reweightings})")
    if not (torch.all(start_attenuation > 0) and torch.all(start_backscatter > 0)):
        raise ValueError("fit_densities: the starting densities must be positive")
    observed = torch.isfinite(ranges) & torch.isfinite(colours).all(dim=-1)
    if int(observed.sum()) == 0:
        raise ValueError("fit_densities: no observations")
    weight = observed.double()
    z = torch.where(observed, ranges, torch.zeros_like(ranges)).double()
    rgb = torch.where(observed[..., None], colours, torch.zeros_like(colours)).double()
    veil = veil.detach().double()
    tied = tie_matrix(tie)
    start_log = torch.log(torch.cat([start_attenuation, start_backscatter]).detach().double())
    observed_weight = weight

    def mean_squared_residual(free: Tensor, weight: Tensor) -> Tensor:
        densities = torch.exp(tied @ free)
        _, predicted = best_colours(z, rgb, weight, densities[:3], densities[3:], veil)
        return ((predicted - rgb) ** 2 * weight[..., None]).sum() / (weight.sum() * 3)

    def fitted_log_densities(start_free: Tensor, weight: Tensor) -> Tensor:
        free = start_free.clone().requires_grad_(True)
        optimizer = torch.optim.LBFGS(
            [free], lr=1.0, max_iter=max_iterations, tolerance_grad=1e-12, tolerance_change=1e-15,
            line_search_fn="strong_wolfe",
        )  # fmt: skip

        def closure() -> Tensor:
            optimizer.zero_grad()
            loss = mean_squared_residual(free, weight)
            loss.backward()
            return loss

        optimizer.step(closure)
        found = free.detach()
        if not torch.isfinite(found).all():
            return start_free  # a diverged search: keep its start
        return newton_polished(lambda f: mean_squared_residual(f, weight), found)

    start_free = ((tied.T @ start_log) / tied.sum(dim=0)).detach()
    free_fit = fitted_log_densities(start_free, weight)
    for _ in range(reweightings):
        with torch.no_grad():
            densities = torch.exp((tied @ free_fit).clamp(-LOG_DENSITY_LIMIT, LOG_DENSITY_LIMIT))
            _, predicted = best_colours(z, rgb, weight, densities[:3], densities[3:], veil)
            weight = cauchy_weights(torch.linalg.vector_norm(predicted - rgb, dim=-1), observed_weight)
        free_fit = fitted_log_densities(free_fit, weight)
    count = weight.sum() * 3
    log_densities = tied @ free_fit
    # 1e-9 to 1e9 per world unit: finite, and finite under inverse softplus
    densities = torch.exp(log_densities.detach().clamp(-LOG_DENSITY_LIMIT, LOG_DENSITY_LIMIT))
    def squared_error_at(log_values: Tensor) -> Tensor:  # per channel, summed over observations
        _, predicted = best_colours(z, rgb, weight, torch.exp(log_values[:3]), torch.exp(log_values[3:]), veil)
        return ((predicted - rgb) ** 2 * weight[..., None]).sum(dim=(0, 1))

    log_fitted = torch.log(densities)
    with torch.no_grad():
        squared_error = squared_error_at(log_fitted)  # of the densities returned, after the clamp
    final = float(squared_error.sum() / count)
    num_points = int((observed.sum(dim=1) >= 2).sum())  # a point seen once says nothing about the medium
    if tied.shape[1] == 6:  # untied
        hessian = torch.autograd.functional.hessian(lambda v: squared_error_at(v).sum(), log_fitted)
        errors = log_density_errors(squared_error, hessian, num_points)
    else:
        free_fitted = (tied.T @ log_fitted) / tied.sum(dim=0)  # exact: tied values are equal
        hessians = torch.stack([
            torch.autograd.functional.hessian(lambda f, c=c: squared_error_at(tied @ f)[c], free_fitted) for c in range(3)
        ])  # fmt: skip
        errors = tied_log_density_errors(squared_error, hessians, tied, num_points)
    return DensityFit(densities[:3], densities[3:], final, *errors)


VEIL_STEP = 0.05
""":func:`veil_sensitivity`'s central difference: the veil scaled by ``e^{±0.05}`` (±5%)."""


def veil_sensitivity(
    ranges: Float[Tensor, "P V"],
    colours: Float[Tensor, "P V 3"],
    veil: Float[Tensor, "3"],
    fit: DensityFit,
    tie: str = "seathru",
) -> Float[Tensor, "3"]:
    """``d ln β_B / d ln B∞`` per channel (dimensionless): how far ``β_B`` moves when the veil it was
    fitted under is off. The SfM observations fix the backscatter's rise over the ranges they span,
    about ``B∞ β_B`` at short range, and hardly ``B∞`` itself (the residual moves by 0.2–2% over a
    veil ×0.8–1.2 on path-traced water; docs/history.md, 2026-11-29), so an error in ``B∞`` passes
    into ``β_B``: one for one at short range (``−1``), more where the observed backscatter
    saturates. On path-traced coastal water it is −2.0, −1.6, −1.5 and on turbid water −5.5, −2.0,
    −2.9 (R, G, B): a veil 10% high there puts ``β_B`` 15–55% low.

    ``fit`` (:func:`fit_densities` of ``ranges``, ``colours`` under ``veil``, tied by ``tie``) is
    refitted under the whole veil scaled by ``e^{±h}``, ``h =`` :data:`VEIL_STEP`, from its own
    densities: ``(ln β_B(+h) − ln β_B(−h)) / 2h``. The refits are the whole robust fit
    (reweighting included), so this is how the estimate itself answers an error in the veil,
    not only the model's. Two fits' cost (a second or two on a few thousand observations)."""
    scale = torch.exp(torch.tensor(VEIL_STEP, dtype=torch.float64))
    refits = [
        fit_densities(ranges, colours, veil.double() * factor, fit.attenuation, fit.backscatter, tie=tie)
        for factor in (scale, 1.0 / scale)
    ]
    return (torch.log(refits[0].backscatter) - torch.log(refits[1].backscatter)) / (2 * VEIL_STEP)


def fit_replaces(fit: DensityFit, max_log_error: float) -> Bool[Tensor, "3"]:
    """Per channel, whether the fit's densities replace the trained ones: where the fit's standard
    error ``s`` of ``ln β_D`` is at most ``max_log_error`` (``research.medium_fit_max_log_error``;
    0.35 is a 95% interval within a factor of 2 either side of the fitted ``β_D``).

    Why the fit's precision alone, and not how far the trained value lies from it: the trained
    attenuation is not an estimate with an error of its own. It starts at the bound from the
    brightest SfM observations, above the truth, and ends on the side of the truth it started from
    (docs/history.md, 2026-11-25): at step 499 on path-traced water and fog it is 1.3-2.1 times the
    truth (log error 0.25-0.74), where fits with ``s`` up to 0.2 are within 25%. A rule that also
    asked whether the fit rejects the trained value (by 1.96 ``s``) made the decision hang on the
    training run: on coastal water's blue (``s`` 0.18-0.20) it replaced in some runs and kept a
    value 28-34% high in others, and one SfM model trained in our layout and in the published one
    ended 26% apart in blue ``β_D`` (docs/history.md, 2026-11-28 (84766a4, d3246d9 and its revert)). The fit's ``s``
    depends only on the observations and the veil, so every data path decides alike.

    A non-finite error replaces nothing (every comparison with NaN or inf is false)."""
    return fit.attenuation_log_error.double() <= max_log_error


def explained_variation(
    ranges: Float[Tensor, "P V"],
    colours: Float[Tensor, "P V 3"],
    veil: Float[Tensor, "3"],
    beta_d: Float[Tensor, "3"],
    beta_b: Float[Tensor, "3"],
) -> Float[Tensor, "3"]:
    """Per channel, the share of how the points' colours change between views that the medium explains:

        1 - Σ (I - J a - B)² / Σ (I - Ī_p)²,

    sums over the observed entries (``NaN`` where not observed), ``J a + B`` the medium's prediction
    with each point's least-squares colour (:func:`best_colours`), ``Ī_p`` the point's mean colour
    (the prediction without a medium). 1: the medium explains every change; 0: none of it, and 0
    where the colours do not change at all (nothing to explain) or the medium fits them worse than no
    medium (the ratio, which may overflow where the change is tiny, is clamped into [0, 1]).
    Densities in 1/world unit, ranges in world units, colours linear."""
    seen = torch.isfinite(ranges) & torch.isfinite(colours).all(dim=-1)
    observed = seen.double()
    z = torch.where(seen, ranges, torch.zeros_like(ranges)).double()
    light = torch.where(seen[..., None], colours, torch.zeros_like(colours)).double()
    no_medium = torch.zeros(3, dtype=torch.float64)

    def squared_residual(attenuation: Tensor, backscatter: Tensor) -> Tensor:
        _, predicted = best_colours(z, light, observed, attenuation, backscatter, veil.double())
        return (((predicted - light) * observed[..., None]) ** 2).sum(dim=(0, 1))

    unexplained = squared_residual(no_medium, no_medium)  # Σ (I - Ī_p)² for colours >= 0
    left = squared_residual(beta_d.double(), beta_b.double())
    share = (1.0 - left / unexplained.clamp_min(1e-300)).clamp(0.0, 1.0)  # -inf (overflow) -> 0
    return torch.where(unexplained > 0, share, torch.zeros_like(share))


def sfm_observation_table(model: Any) -> Any:
    """The dataparser's SfM observation table of ``model``, or ``None`` if it has no observation."""
    table = (model.kwargs.get("metadata") or {}).get(SFM_OBSERVATIONS_KEY)
    return table if table is not None and table.num_observations > 0 else None


def fit_model_medium(model: Any, table: Any, tie: str) -> tuple[Tensor, Tensor, DensityFit]:
    """:func:`fit_densities` on ``table`` under the veiling light ``model`` has learned, started at
    its densities. Returns ``(densities, veil, fit)``: the model's densities (1/world unit,
    ``β_D`` then ``β_B``) and veil before the fit, and the fit.

    The last fit is kept on the model (``model.last_medium_fit``) with its inputs, and returned
    again while the tie, the densities and the veil are bitwise the same: ``auto``'s evidence and
    the fit that follows at the same step then cost one fit, not two."""
    medium = model.medium_field
    with torch.no_grad():
        densities = torch.nn.functional.softplus(medium.density_raw.double()) * model.world_scale
        veil = torch.sigmoid(medium.rgb_logit.double())
    last = getattr(model, "last_medium_fit", None)
    if last is not None and last[0] == tie and torch.equal(last[1], densities) and torch.equal(last[2], veil):
        return densities, veil, last[3]
    fit = fit_densities(
        torch.from_numpy(table.ranges), torch.from_numpy(table.colours), veil, densities[:3], densities[3:], tie=tie
    )
    model.last_medium_fit = (tie, densities, veil, fit)
    return densities, veil, fit


def apply_medium_fit(model: Any, step: int, optimizers: Any = None) -> None:
    """The ``medium_fit_step`` callback: replace the scene medium's densities by
    :func:`fit_densities` on the dataparser's SfM observation table, under the veiling light learned
    so far, tied as the medium model in use renders them, and hold them from then on
    (``model.densities_fitted``), moving from the trained values to the fit in log space over
    ``research.auto_blend_steps`` (:meth:`~seathru_nerfstudio.medium_field.SceneMedium.move_to_fit`).
    Set at once, the fit's change of the image emptied the object field within 15 steps on
    path-traced coastal water (opacity 0.65 → 0.14–0.19 on three runs of seed 42, depth error 0.1 →
    0.9–1.5; 0.63 with the move; docs/history.md, 2026-11-29). A channel the fit is uncertain about
    (standard error of ``ln β_D`` above ``research.medium_fit_max_log_error``; :func:`fit_replaces`)
    keeps its trained densities and trains on.
    ``optimizers``: the trainer's, whose ``medium_density`` Adam state is cleared."""
    config = model.config
    after_fit = step - (config.medium_fit_step or 0) + 1  # 0 at the fit's own step (its last, 499)
    if model.fits_medium and 0 < after_fit <= config.research.auto_blend_steps:  # the held densities move to the fit
        model.medium_field.move_to_fit(after_fit / max(config.research.auto_blend_steps, 1), model.densities_fitted.cpu())
    if not (model.fits_medium and TrainingPhases(config, step).ends(config.medium_fit_step)):
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
        fit = fit_densities(
            torch.from_numpy(table.ranges), torch.from_numpy(table.colours), veil, fit.attenuation, fit.backscatter,
            tie=model.medium_model,
        )
    model.fit_log_error.copy_(fit.attenuation_log_error.to(model.fit_log_error))
    model.fit_backscatter_log_error.copy_(fit.backscatter_log_error.to(model.fit_backscatter_log_error))
    sensitivity = veil_sensitivity(torch.from_numpy(table.ranges), torch.from_numpy(table.colours), veil, fit, model.medium_model)
    model.backscatter_veil_sensitivity.copy_(torch.nan_to_num(sensitivity, nan=0.0, posinf=0.0, neginf=0.0).to(model.backscatter_veil_sensitivity))
    uncertain = ~fit_replaces(fit, config.research.medium_fit_max_log_error)
    show = lambda values: ", ".join(f"{float(v):.3g}" for v in values)  # noqa: E731
    if uncertain.all() and model.fit_oracle is None:  # nothing to replace: leave the parameters and Adam alone
        CONSOLE.print(
            f"[bold]seathru step {step}: medium fit to {table.num_observations} SfM observations kept the trained "
            f"densities: the fit is imprecise (standard error of ln beta_D {show(fit.attenuation_log_error)} above "
            f"{config.research.medium_fit_max_log_error:g}; fitted beta_D {show(fit.attenuation)} /m)"
        )
        return
    beta_d = torch.where(uncertain, densities[:3], fit.attenuation)
    beta_b = torch.where(uncertain, densities[3:], fit.backscatter)
    replaced = torch.cat([~uncertain, ~uncertain])
    if model.fit_oracle is not None:  # diagnostic: the truth in place of the fit, held like it
        parts = config.research.medium_fit_oracle_parts
        beta_d, beta_b, replaced = replace_with_truth(model.fit_oracle, parts, beta_d, beta_b, ~uncertain)
        CONSOLE.print(f"[bold]seathru step {step}: medium_fit_oracle: the true densities ({parts}) replace the fit")
    fitted = torch.cat([beta_d, beta_b]) / model.world_scale
    medium.start_move_to_fit(fitted, surface_veil)  # reached after auto_blend_steps
    if optimizers is not None and "medium_density" in optimizers.optimizers:
        optimizers.optimizers["medium_density"].state.clear()  # Adam's moments were for the old values
    model.densities_fitted.copy_(replaced.to(model.densities_fitted.device))
    CONSOLE.print(
        f"[bold]seathru step {step}: medium fitted to {table.num_observations} SfM observations ({model.medium_model} tie)[/] "
        f"(residual {fit.residual:.3g}): beta_D {show(densities[:3])} -> {show(beta_d)} /m, "
        f"beta_B {show(densities[3:])} -> {show(beta_b)} /m, under B_inf {show(veil)}; "
        f"standard error of ln beta_D {show(fit.attenuation_log_error)}, of ln beta_B {show(fit.backscatter_log_error)}; "
        f"beta_B moves {show(sensitivity)} times any relative error of B_inf"
        + (f", kept the trained values of channel(s) {uncertain.nonzero().flatten().tolist()}" if uncertain.any() else "")
    )
