"""Which stage of training a step is in: one pure object that answers every schedule question.

The timeline of a medium model (defaults in brackets)::

    0 ─ first stage ─ 200 ─ full model ─ 500 ─ blend ─ 700 ─ full model ─ end
    │   image shows an       object field   auto decides,    medium moves to auto's
    │   empty scene: the     enters; strong medium fitted    choice, object density
    │   veiling light and    binary prior;  to the SfM       held; (``none`` here: the
    │   the SfM geometry     backscatter    points, then     object field restarts
    │   learn                excess loss    held             as nerfacto, no blend)
    └ auto: ``none`` before training if the SfM fit explains too little; the run is ``none`` throughout

* ``medium_first_steps`` (200): the object colour waits; the object *density* learns from the SfM
  depths and the empty-space prior; every ray shows the veiling light. Over its second half the
  colour of the rays that geometry leaves open is averaged; at its end it becomes the veiling
  light, held from then on. At its end the backscatter density is capped by the darkest SfM observations and
  the attenuation by the brightest (:mod:`seathru_nerfstudio.medium_start`).
* ``research.auto_decision_step`` (500, ``auto`` only): the simplest medium model the evidence of
  the last ``research.auto_evidence_steps`` allows (:mod:`seathru_nerfstudio.medium_choice`).
* ``medium_fit_step`` (500, after the decision): the densities are fitted to the SfM observations
  under the veiling light learned so far (:mod:`seathru_nerfstudio.medium_fit`) and held from then on,
  moving from their trained values to the fit over ``research.auto_blend_steps``.
  Up to this step the binary prior has its strong early weight (the open water stays empty while
  the veiling light is read), afterwards the paper's λ.
* ``research.auto_blend_steps`` (200): after a decision other than ``seathru`` or ``none``, the
  medium moves linearly to the chosen model while the object density is held.
* ``research.backscatter_excess_steps`` (500): the backscatter excess loss applies before this.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

if TYPE_CHECKING:
    from seathru_nerfstudio.model_config import SeathruModelConfig


@dataclass(frozen=True)
class TrainingPhases:
    """The schedule at one step. ``step``: the trainer's step, ``None`` outside training (a loaded
    model, evaluation, the viewer: everything is at its end state). ``blend_start``: the step at
    which ``auto``'s blend began (-1: no blend)."""

    config: "SeathruModelConfig"
    step: Optional[int]
    blend_start: int = -1

    @property
    def first_stage(self) -> bool:
        """In the first ``medium_first_steps`` steps, where the image shows an empty scene."""
        return self.step is not None and self.step < self.config.medium_first_steps

    @property
    def reads_open_water(self) -> bool:
        """In the second half of the first stage, where its geometry has formed: the open rays' colour is averaged."""
        return self.first_stage and self.step >= self.config.medium_first_steps // 2

    @property
    def reads_surface_veil(self) -> bool:
        """From half way between the first stage's end and ``medium_fit_step`` up to the fit: the rays that end
        on a surface are counted for the veil in front of the surfaces (:mod:`seathru_nerfstudio.surface_veil`)."""
        fit_step = self.config.medium_fit_step
        if self.step is None or fit_step is None or self.config.research.surface_veil_optical_depth is None:
            return False
        return (self.config.medium_first_steps + fit_step) // 2 <= self.step < fit_step

    @property
    def after_first_stage(self) -> bool:
        """In training, once a first stage is over (the veiling light read there is held)."""
        first = self.config.medium_first_steps
        return self.step is not None and first > 0 and self.step >= first

    @property
    def medium_blend(self) -> float:
        """How far the medium has moved to ``auto``'s choice: ``(step - blend_start) / blend_steps``
        clipped to ``[0, 1]``; 1 without a blend and outside training."""
        steps = self.config.research.auto_blend_steps
        if self.blend_start < 0 or self.step is None or steps <= 0:
            return 1.0
        return min(1.0, max(0.0, (self.step - self.blend_start) / steps))

    @property
    def binary_prior_weight(self) -> float:
        """The binary prior's weight: ``research.binary_prior_early_mult`` before ``medium_fit_step``
        (throughout when there is no fit), ``binary_prior_mult`` after it and outside training."""
        early = self.config.research.binary_prior_early_mult
        if early is None or self.step is None:
            return self.config.binary_prior_mult
        fit_step = self.config.medium_fit_step
        return early if fit_step is None or self.step < fit_step else self.config.binary_prior_mult

    @property
    def backscatter_excess_active(self) -> bool:
        """Whether the backscatter excess loss applies in a training pass: weight > 0, and before its
        last step (or no step known: a model trained without nerfstudio's trainer)."""
        research = self.config.research
        if research.backscatter_excess_mult <= 0:
            return False
        return self.step is None or self.step < research.backscatter_excess_steps

    def ends(self, stage_length: Optional[int]) -> bool:
        """Whether this step is the last of a stage ``stage_length`` steps long (the callbacks
        after iteration ``step`` act for ``step + 1`` steps done)."""
        return self.step is not None and stage_length is not None and self.step + 1 == stage_length

    def reached(self, stage_length: int) -> bool:
        """Whether ``stage_length`` steps are done after this step."""
        return self.step is not None and self.step + 1 >= stage_length
