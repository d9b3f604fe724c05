"""``medium_model=auto``: keep the simplest medium model that explains the scene.

A run with ``auto`` trains the full ``seathru`` medium through a warm-up, then reads what it
learned (:class:`MediumEvidence`, averaged over the last steps of the warm-up) and keeps the
simplest model of :data:`~seathru_nerfstudio.medium_field.MEDIUM_MODELS` that the evidence
allows (:func:`choose_medium_model`). Where the dataparser has SfM observations, the densities
of the evidence are those of the medium fit (:func:`~seathru_nerfstudio.medium_fit.fit_densities`,
six free, under the veiling light learned so far), not the warm-up's: the warm-up's backscatter
density sits at the cap from the darkest pixels, and on the path-traced fog it was 0.03 /m
against a fitted 0.07 and a true 0.09, so the densities looked coloured and unequal.

1. ``none`` if the medium does not explain the scene. Where there are SfM observations, that is
   the share of how the surfaces' colours change between views that the medium fit explains
   (:func:`~seathru_nerfstudio.medium_fit.explained_variation`, in the channel where it explains
   most), below :attr:`ChoiceRule.none_below_explained`. A medium changes a surface's colour with
   its range; clear air does not, whatever its background. The backscatter share cannot tell: on
   path-traced clear air with a bright sky the fit put 14-18% of the light in backscatter (the sky,
   learned as veiling light, and the colour changes that a pixel's footprint makes between views,
   which converge on a neighbourhood's mean as a medium's converge on its veil), yet it explains
   1.2% of the change; path-traced coastal water 12%, turbid 10%, fog 14%, the formula demos 32-37%
   (0.03% the clear demo; docs/history.md, 2026-11-27). This test needs no training, so it is made
   before the first step (:meth:`AutoMediumChoice.clear_air_before_training`), and again at the
   decision step. Without SfM observations, the warm-up's
   backscatter share of the image must reach :attr:`ChoiceRule.none_below_share` for a medium: every
   scattering medium that is lit shows backscatter, and without it the attenuation is not
   identifiable (the object colour can absorb it).
2. ``fog`` if the densities are grey: the attenuation's channels within
   :attr:`ChoiceRule.grey_attenuation_ratio`, the backscatter density's within the looser
   :attr:`ChoiceRule.grey_backscatter_ratio`.
   Fog and haze attenuate independently of wavelength (the paper, sec. 3); water absorbs red first
   (the demos: ratios 1.4-1.6, path-traced coastal water 2.5). The veiling light is no test: it
   takes the illuminant's colour (blue under a sky: 1.44 on the path-traced fog), and neither is
   ``β_D = β_B``: with forward scattering the best-fitting backscatter density of the path-traced
   fog is 0.72 of its attenuation (docs/history.md, 2026-11-27).
3. ``uniform`` if attenuation and backscatter agree per channel: where the scene's far range
   is known (the SfM bounds), if tying them changes the light from the farthest surfaces by
   less than :attr:`ChoiceRule.tie_optical_depth` in optical depth; else, if their ratio is
   close to 1. A ratio alone is blind to distance: turbid water with attenuation 1.3x its
   backscatter (the ``turbid`` demo's truth, ratio 1.29) ties within 1.3x, yet over its
   8 m the tie dims the far surfaces' light by e^{-1.1}, a factor 3.
4. ``seathru`` otherwise.

The thresholds are ratios (largest over smallest) or optical depths (density times range),
so they do not depend on units.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch

from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio.diagnostics import CHANNELS
from seathru_nerfstudio.medium_field import MEDIUM_MODELS
from seathru_nerfstudio.medium_fit import explained_variation, fit_model_medium, fit_replaces, sfm_observation_table
from seathru_nerfstudio.phases import TrainingPhases

RGB = Tuple[float, float, float]
UNDECIDED = -1
"""``medium_model_code`` of an ``auto`` run before its decision (it renders ``seathru``)."""


@dataclass(frozen=True)
class MediumEvidence:
    """What the warm-up learned: the ``seathru`` medium, averaged over its last steps."""

    backscatter_share: float
    """Backscatter over the in-medium image (sum over the rays of a batch), in [0, 1]."""
    beta_D: RGB
    """Attenuation per channel, 1/world unit."""
    beta_B: RGB
    """Backscatter density per channel, 1/world unit."""
    B_inf: RGB
    """Veiling light per channel, linear."""
    far_range: Optional[float] = None
    """Range of the farthest surfaces (the SfM far bound), world units; ``None``: unknown."""
    explained: Optional[float] = None
    """The largest share over the channels of the SfM points' colour change between views that the
    medium fit explains (:func:`~seathru_nerfstudio.medium_fit.explained_variation`); ``None``:
    no fit."""


@dataclass(frozen=True)
class ChoiceRule:
    """Thresholds of :func:`choose_medium_model`."""

    none_below_explained: float = 0.05
    """With a medium fit, ``none`` where it explains less than this share of the colour change."""
    none_below_share: float = 0.02
    """Without one, ``none`` below this backscatter share of the image."""
    grey_attenuation_ratio: float = 1.25
    """``fog`` needs the attenuation's channels within this ratio of each other."""
    grey_backscatter_ratio: float = 1.5
    """... and the backscatter density's within this one: looser, since it also carries the colour
    of the light that scatters (1.23 fitted on the path-traced fog, whose attenuation is grey). Evidence
    only: the ``fog`` model keeps a backscatter density per channel."""
    tie_ratio: float = 1.3
    """Without a far range, ``uniform`` needs attenuation and backscatter within this ratio,
    channel by channel."""
    tie_optical_depth: float = 0.1
    """With a far range, ``uniform`` needs ``|beta_D - beta_B| * far_range`` at most this in
    every channel: tying them then changes the farthest surfaces' light by at most
    ``e^0.1 - 1``, about 10%."""


def _ratio(values: Sequence[float]) -> float:
    """Largest over smallest; ``inf`` if the smallest is not above 0."""
    low, high = min(values), max(values)
    return high / low if low > 0 else float("inf")


def choose_medium_model(evidence: MediumEvidence, rule: ChoiceRule = ChoiceRule()) -> Tuple[str, str]:
    """The simplest medium model the evidence allows, and why, in one readable phrase."""
    share, explained = evidence.backscatter_share, evidence.explained
    if explained is not None:
        if explained < rule.none_below_explained:
            return "none", f"the medium explains {explained:.3f} < {rule.none_below_explained:g} of the colour change"
        shown = f"the medium explains {explained:.3f} of the colour change"
    elif share < rule.none_below_share:
        return "none", f"backscatter share {share:.3f} < {rule.none_below_share:g}"
    else:
        shown = f"backscatter share {share:.3f}"
    grey, grey_backscatter = _ratio(evidence.beta_D), _ratio(evidence.beta_B)
    facts = f"{shown}, attenuation ratio {grey:.2f}, backscatter density ratio {grey_backscatter:.2f}"
    if grey <= rule.grey_attenuation_ratio and grey_backscatter <= rule.grey_backscatter_ratio:
        return "fog", f"{facts}: grey (<= {rule.grey_attenuation_ratio:g}, {rule.grey_backscatter_ratio:g})"
    far = evidence.far_range
    if far is not None and math.isfinite(far) and far > 0:
        gap = max(abs(d - b) for d, b in zip(evidence.beta_D, evidence.beta_B)) * far
        facts += f", attenuation-backscatter gap {gap:.2f} in optical depth at the far range {far:.3g}"
        if gap <= rule.tie_optical_depth:
            return "uniform", f"{facts}: attenuation ties to backscatter (<= {rule.tie_optical_depth:g})"
    else:
        ties = max(_ratio((d, b)) for d, b in zip(evidence.beta_D, evidence.beta_B))
        facts += f", attenuation/backscatter ratio {ties:.2f}"
        if ties <= rule.tie_ratio:
            return "uniform", f"{facts}: attenuation ties to backscatter (<= {rule.tie_ratio:g})"
    return "seathru", f"{facts}: no simpler model fits"


def _fit_and_explained_share(model: Any, table: Any) -> Tuple[Any, float]:
    """The medium fit (six free) to the SfM observation table under the veiling light the model has
    now, and the largest share over the channels of the points' colour change it explains."""
    _, veil, fit = fit_model_medium(model, table, tie="seathru")
    ranges, colours = torch.from_numpy(table.ranges), torch.from_numpy(table.colours)
    return fit, float(explained_variation(ranges, colours, veil, fit.attenuation, fit.backscatter).max())


def _state_copy(module: torch.nn.Module) -> Dict[str, torch.Tensor]:
    return {name: value.detach().clone() for name, value in module.state_dict().items()}


class AutoMediumChoice:
    """``auto`` in training, as a callback: it gathers :class:`MediumEvidence` over the
    ``research.auto_evidence_steps`` before ``research.auto_decision_step``, then sets the model's
    ``medium_model_code`` to :func:`choose_medium_model`'s choice. Only the tying of the medium
    changes; for ``none`` decided there the object field and the proposal networks restart from
    their initial state (what they learned under a medium makes up for an attenuation clear air
    does not have), and for ``fog``/``uniform``/``basic`` the model blends from ``seathru``
    (``medium_model_step``). Where the SfM fit shows clear air, ``none`` is decided before training
    (:meth:`clear_air_before_training`), with nothing to restart."""

    def __init__(self, model: Any) -> None:
        self.model = model
        self.evidence: List[MediumEvidence] = []
        self.initial_object: Optional[Dict[str, Dict[str, torch.Tensor]]] = {
            "field": _state_copy(model.field),
            "proposal_networks": _state_copy(model.proposal_networks),
        }
        """Copies of the object field's and the proposal networks' state to restart ``none`` from."""

    @property
    def decided(self) -> bool:
        return int(self.model.medium_model_code) != UNDECIDED

    def record(self, values: Dict[str, torch.Tensor], step: Optional[int]) -> None:
        """Keep this step's medium diagnostics (:func:`seathru_nerfstudio.diagnostics.decomposition`)
        if the decision is near."""
        research = self.model.config.research
        if self.decided or step is None or step < research.auto_decision_step - research.auto_evidence_steps:
            return

        def rgb(name: str) -> RGB:
            return tuple(float(values[f"medium_{name}_{c}"]) for c in CHANNELS)  # type: ignore[return-value]

        self.evidence.append(
            MediumEvidence(
                backscatter_share=float(values["backscatter_share"]),
                beta_D=rgb("beta_D"),
                beta_B=rgb("beta_B"),
                B_inf=rgb("B_inf"),
            )
        )

    def mean_evidence(self) -> Optional[MediumEvidence]:
        """The mean of the recorded evidence over every process of a distributed run (so that all
        of them choose the same model); ``None`` if nothing was recorded."""
        if not self.evidence:
            return None
        rows = torch.tensor(
            [[e.backscatter_share, *e.beta_D, *e.beta_B, *e.B_inf] for e in self.evidence], dtype=torch.float64
        )
        mean = rows.mean(dim=0)
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            mean = mean.to(self.model.device)
            torch.distributed.all_reduce(mean)
            mean = mean.cpu() / torch.distributed.get_world_size()
        v = [float(x) for x in mean]
        return MediumEvidence(
            backscatter_share=v[0], beta_D=tuple(v[1:4]), beta_B=tuple(v[4:7]), B_inf=tuple(v[7:10]),  # type: ignore[arg-type]
            far_range=self.model.far_range,
        )

    def fitted_evidence(self, evidence: MediumEvidence) -> Tuple[MediumEvidence, str]:
        """``evidence`` with the share of the SfM points' colour change that the medium fit (six
        free) explains, and its densities channel by channel where they replace the warm-up's
        (:func:`~seathru_nerfstudio.medium_fit.fit_replaces`); and where they come from, in
        words. The explained share needs no such bound: where the fit cannot split ``β_D`` from
        ``β_B`` its log-errors are large, but how much of the change the pair explains is not."""
        model = self.model
        table = sfm_observation_table(model)
        if not model.fits_medium or table is None:
            return evidence, "from the warm-up (no SfM fit)"
        fit, explained = _fit_and_explained_share(model, table)
        evidence = dataclasses.replace(evidence, explained=explained)
        certain = fit_replaces(fit, model.config.research.medium_fit_max_log_error)
        if not bool(certain.any()):
            return evidence, "from the warm-up (the SfM fit is uncertain)"

        def merged(fitted: torch.Tensor, warm_up: RGB) -> RGB:
            return tuple(float(f) if c else w for f, c, w in zip(fitted, certain, warm_up))  # type: ignore[return-value]

        chosen = dataclasses.replace(
            evidence, beta_D=merged(fit.attenuation, evidence.beta_D), beta_B=merged(fit.backscatter, evidence.beta_B)
        )
        return chosen, f"from the SfM fit ({int(certain.sum())} of 3 channels)"

    def clear_air_before_training(self, step: int) -> bool:
        """Before the first training step, where there are SfM observations: decide ``none`` already if
        the medium fit explains too little of their colour change (rule 1). The run is then ``none``
        from its first step, as if it had been asked for. Returns whether it decided.

        The share needs no training: six free densities absorb the veiling light the fit is given. In
        its best channel, under the untrained grey veil (0.5) against the veil learned by step 499:
        path-traced clear air 0.013 (0.013), coastal water 0.113 (0.118), fog 0.145 (0.144), the water
        and fog demos 0.370 and 0.328 (0.368, 0.318), the clear demo 0.0003 (0.0003)
        (docs/history.md, 2026-11-28). Deciding at the decision step instead restarted the object
        field there, 500 steps into the run: ``none`` forced from step 0 gave 32.27 dB on path-traced
        clear air against 31.89 with the restart, 34.26 against 33.49 on the clear demo."""
        model = self.model
        if self.decided or step != 0 or not model.fits_medium:
            return False
        table = sfm_observation_table(model)
        if table is None:
            return False
        _, explained = _fit_and_explained_share(model, table)
        rule = model.config.research.auto_rule
        if explained >= rule.none_below_explained:
            CONSOLE.print(
                f"seathru: the medium explains {explained:.3f} of the SfM points' colour change "
                f"(>= {rule.none_below_explained:g}); auto decides at step {model.config.research.auto_decision_step}"
            )
            return False
        model.medium_model_code.fill_(MEDIUM_MODELS.index("none"))
        model.fit_object_field_to_medium_model()
        self.initial_object = None
        CONSOLE.print(
            f"[bold]seathru: medium model auto -> none[/] (the medium explains {explained:.3f} < "
            f"{rule.none_below_explained:g} of the SfM points' colour change, before training)"
        )
        return True

    def after_step(self, step: int, optimizers: Any = None) -> None:
        """At ``research.auto_decision_step``: decide. ``optimizers``: the trainer's, whose state of the
        restarted parameter groups is cleared."""
        model = self.model
        if self.decided or not TrainingPhases(model.config, step).reached(model.config.research.auto_decision_step):
            return
        evidence = self.mean_evidence()
        if evidence is None:
            return  # resumed right before the decision: gather the evidence first
        evidence, source = self.fitted_evidence(evidence)
        chosen, reason = choose_medium_model(evidence, model.config.research.auto_rule)
        reason += f"; densities {source}"
        model.medium_model_code.fill_(MEDIUM_MODELS.index(chosen))
        if chosen == "none" and self.initial_object is not None:
            model.field.load_state_dict(self.initial_object["field"])
            model.proposal_networks.load_state_dict(self.initial_object["proposal_networks"])
            model.fit_object_field_to_medium_model()
            for group in ("fields", "proposal_networks"):
                if optimizers is not None and group in optimizers.optimizers:
                    optimizers.optimizers[group].state.clear()  # Adam restarts with the parameters
            reason += "; the object field restarts from its initial state"
        elif chosen != "seathru":  # the warm-up's own model: nothing to blend
            model.medium_model_step.fill_(step + 1)
        self.initial_object = None
        self.evidence.clear()
        CONSOLE.print(f"[bold]seathru step {step}: medium model auto -> {chosen}[/] ({reason})")
