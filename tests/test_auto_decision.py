"""``auto``'s choice of a medium model (issue 10): the decision rule on synthetic evidence, when and from what it
decides (the SfM fit, the points before training), and what follows a choice (the blend, the restart, the prior)."""

from __future__ import annotations

import dataclasses
from typing import Optional

import pytest
import numpy as np
import torch

from nerfstudio.engine.optimizers import AdamOptimizerConfig, Optimizers

from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY
from seathru_nerfstudio.medium_choice import ChoiceRule, MediumEvidence, choose_medium_model
from seathru_nerfstudio.medium_field import MEDIUM_MODELS, tie
from seathru_nerfstudio.model import UNDECIDED
from seathru_nerfstudio.phases import TrainingPhases
from seathru_nerfstudio.losses import binary_transmittance_loss

from tiny_training import rays, tiny_model

from test_medium_models import losses_of


def evidence(share=0.3, beta_D=(1.3, 1.2, 0.9), beta_B=(0.95, 0.85, 0.7), B_inf=(0.07, 0.2, 0.39), far_range=None, explained=None):
    return MediumEvidence(
        backscatter_share=share, beta_D=beta_D, beta_B=beta_B, B_inf=B_inf, far_range=far_range, explained=explained
    )


@pytest.mark.parametrize(
    "case, expected",
    [
        (evidence(), "seathru"),  # the water demo's true medium
        (evidence(share=0.005), "none"),  # no backscatter: whatever the densities say
        (evidence(share=0.019), "none"),
        # with a medium fit, what it explains decides, not the share: path-traced clear air's sky
        (evidence(share=0.3, explained=0.013), "none"),
        (evidence(share=0.005, explained=0.4), "seathru"),
        (evidence(share=0.3, explained=0.12, beta_D=(0.12,) * 3, beta_B=(0.08, 0.07, 0.065)), "fog"),
        (evidence(share=0.021, beta_D=(1.2,) * 3, beta_B=(1.2,) * 3, B_inf=(0.6,) * 3), "fog"),
        (evidence(beta_D=(1.3, 1.25, 1.1), beta_B=(1.2, 1.3, 1.0), B_inf=(0.6, 0.58, 0.55)), "fog"),
        (evidence(beta_D=(1.0, 2.0, 1.0), beta_B=(1.0, 2.0, 1.0), B_inf=(0.6,) * 3), "uniform"),  # grey, not fog
        (evidence(beta_D=(1.2,) * 3, beta_B=(1.2,) * 3), "fog"),  # a blue veil is the light's colour: still fog
        (evidence(beta_D=(0.12,) * 3, beta_B=(0.08, 0.07, 0.065), B_inf=(0.26, 0.31, 0.41)), "fog"),  # path-traced fog's fit
        (evidence(beta_D=(1.3, 0.9, 0.5), beta_B=(1.2, 1.0, 0.45)), "uniform"),
        (evidence(beta_D=(1.3, 0.9, 0.5), beta_B=(1.3, 0.9, 0.7)), "seathru"),  # blue ratio 1.4
        (evidence(beta_D=(1.0,) * 3, beta_B=(0.0, 1.0, 1.0), B_inf=(0.6,) * 3), "seathru"),  # a zero density
    ],
)
def test_decision_rule_on_synthetic_evidence(case, expected):
    chosen, reason = choose_medium_model(case)
    assert chosen == expected, reason
    assert reason


def test_decision_rule_thresholds_are_the_rules():
    water = evidence()
    assert choose_medium_model(water, ChoiceRule(tie_ratio=1.5))[0] == "uniform"
    assert choose_medium_model(water, ChoiceRule(none_below_share=0.5))[0] == "none"
    fitted = dataclasses.replace(water, explained=0.3)
    assert choose_medium_model(fitted, ChoiceRule(none_below_share=0.5))[0] == "seathru"
    assert choose_medium_model(fitted, ChoiceRule(none_below_explained=0.5))[0] == "none"
    grey = evidence(beta_D=(1.0, 1.1, 1.2), beta_B=(1.0, 1.1, 1.2), B_inf=(0.5, 0.55, 0.6))
    assert choose_medium_model(grey)[0] == "fog"
    assert choose_medium_model(grey, ChoiceRule(grey_attenuation_ratio=1.1))[0] == "uniform"


def test_a_known_far_range_ties_by_optical_depth_not_by_ratio():
    """The turbid demo's true medium (attenuation 1.29x the backscatter in red): the ratio rule
    ties it, but over 8 m the tie dims the far surfaces by e^{-(0.62-0.48)*8} = e^{-1.12}."""
    turbid = evidence(beta_D=(0.62, 0.38, 0.46), beta_B=(0.48, 0.32, 0.38), B_inf=(0.04, 0.26, 0.18))
    assert choose_medium_model(turbid)[0] == "uniform"  # no far range: the ratio rule
    far = dataclasses.replace(turbid, far_range=8.0)
    chosen, reason = choose_medium_model(far)
    assert chosen == "seathru" and "1.12" in reason, reason
    # The same gap over a short range is within the tolerance: 0.14 /m * 0.7 m = 0.098 <= 0.1.
    assert choose_medium_model(dataclasses.replace(turbid, far_range=0.7))[0] == "uniform"
    assert choose_medium_model(dataclasses.replace(turbid, far_range=0.75))[0] == "seathru"  # 0.105
    assert choose_medium_model(dataclasses.replace(turbid, far_range=0.75), ChoiceRule(tie_optical_depth=0.2))[0] == "uniform"
    # A ratio far from 1 at tiny densities is still a tie when the light hardly changes.
    faint = evidence(beta_D=(0.02, 0.03, 0.04), beta_B=(0.01, 0.01, 0.01), far_range=2.0)
    assert choose_medium_model(faint)[0] == "uniform"
    # Fog is decided before the tie, as without a far range.
    fog = evidence(beta_D=(1.2,) * 3, beta_B=(1.2,) * 3, B_inf=(0.6,) * 3, far_range=8.0)
    assert choose_medium_model(fog)[0] == "fog"
    # A far range that says nothing (0, inf, nan) falls back to the ratio rule.
    for unknown in (0.0, float("inf"), float("nan")):
        assert choose_medium_model(dataclasses.replace(turbid, far_range=unknown))[0] == "uniform"


def feed_evidence(model, values: MediumEvidence, steps: range) -> None:
    for step in steps:
        model.train_step = step
        row = {"backscatter_share": torch.tensor(values.backscatter_share)}
        for name in ("beta_D", "beta_B", "B_inf"):
            for channel, value in zip("rgb", getattr(values, name)):
                row[f"medium_{name}_{channel}"] = torch.tensor(value)
        model.auto_choice.record(row, step)


def test_auto_takes_the_clear_air_objective_at_once_when_it_chooses_none():
    model = tiny_model(medium_model="auto", medium_first_steps=10, auto_decision_step=40)
    feed_evidence(model, evidence(share=0.0), range(20, 40))
    model.auto_choice.after_step(39)
    for step in (40, 140):
        model.train_step = step
        losses, out, target = losses_of(model, seed=step)
        assert "binary_prior_loss" not in losses, step
        torch.testing.assert_close(losses["rgb_loss"], torch.mean((out["rgb"] - target) ** 2), msg=str(step))


def test_auto_decides_once_at_its_step_from_the_mean_evidence_and_checkpoints_record_it():
    model = tiny_model(
        medium_model="auto",
        medium_first_steps=10,
        auto_decision_step=40,
        auto_evidence_steps=20,
    )
    assert model.medium_model == "seathru" and int(model.medium_model_code) == UNDECIDED
    field_before = {k: v.clone() for k, v in model.field.state_dict().items()}
    # early evidence is ignored: only the last 20 steps count
    feed_evidence(model, evidence(), range(0, 20))
    feed_evidence(model, evidence(share=0.0), range(20, 30))
    feed_evidence(model, evidence(share=0.03), range(30, 40))  # mean 0.015: none
    model.auto_choice.after_step(38)
    assert int(model.medium_model_code) == UNDECIDED
    model.auto_choice.after_step(39)
    assert model.medium_model == "none"
    for key, value in model.field.state_dict().items():
        torch.testing.assert_close(value, field_before[key])  # none restarts it from its initial state
    feed_evidence(model, evidence(), range(40, 60))
    model.auto_choice.after_step(59)
    assert model.medium_model == "none"  # decided once

    state = model.state_dict()
    assert int(state["medium_model_code"]) == MEDIUM_MODELS.index("none")
    fresh = tiny_model(medium_model="auto", medium_first_steps=10, auto_decision_step=40)
    fresh.load_state_dict(state)
    assert fresh.medium_model == "none"


def test_auto_keeping_seathru_changes_nothing():
    model = tiny_model(medium_model="auto", medium_first_steps=10, auto_decision_step=40)
    feed_evidence(model, evidence(), range(20, 40))
    model.auto_choice.after_step(39)
    model.train_step = 41
    assert model.medium_model == "seathru" and model.medium_blend == 1.0


@pytest.mark.parametrize("far_scene_units, expected", [(0.5 * 0.25, "uniform"), (8.0 * 0.25, "seathru")])
def test_auto_weighs_the_tie_over_the_dataparser_far_bound_in_world_units(far_scene_units, expected):
    """Scale 0.25 scene units per metre: a far bound of 2 scene units is 8 m, where the turbid
    truth's gap (0.14 /m) is 1.12 in optical depth; at 0.5 m it is 0.07, a tie."""
    metadata = {SCALE_KEY: 0.25, "near_plane": 0.05, "far_plane": far_scene_units}
    model = tiny_model(metadata, medium_model="auto", medium_first_steps=10, auto_decision_step=40)
    assert model.far_range == pytest.approx(far_scene_units / 0.25)
    turbid = evidence(beta_D=(0.62, 0.38, 0.46), beta_B=(0.48, 0.32, 0.38), B_inf=(0.04, 0.26, 0.18))
    feed_evidence(model, turbid, range(20, 40))
    model.auto_choice.after_step(39)
    assert model.medium_model == expected


def test_auto_settings_are_checked():
    with pytest.raises(ValueError, match="auto-decision-step"):
        tiny_model(medium_model="auto", medium_first_steps=200, auto_decision_step=100)


def _object_values(model) -> dict:
    return {
        name: value.clone()
        for name, value in list(model.field.state_dict().items())
        + [(f"proposal.{k}", v) for k, v in model.proposal_networks.state_dict().items()]
    }


def _perturb_object(model) -> None:
    """What the warm-up's training would do to the object field and the proposal networks."""
    with torch.no_grad():
        for parameter in list(model.field.parameters()) + list(model.proposal_networks.parameters()):
            parameter.add_(0.5)


def _optimizers_with_state(model) -> Optimizers:
    """The trainer's optimisers, after one step (so that Adam has state)."""
    config = {name: {"optimizer": AdamOptimizerConfig(lr=1e-3), "scheduler": None} for name in model.get_param_groups()}
    optimizers = Optimizers(config, model.get_param_groups())
    for group in model.get_param_groups().values():
        for parameter in group:
            parameter.grad = torch.ones_like(parameter)
    optimizers.optimizer_step_all()
    return optimizers


@pytest.mark.parametrize("share, chosen", [(0.0, "none"), (0.5, "seathru")])
def test_auto_choosing_none_restarts_the_object_field_and_its_optimiser(share, chosen):
    model = tiny_model(medium_model="auto", medium_first_steps=10, auto_decision_step=40)
    initial = _object_values(model)
    _perturb_object(model)  # the warm-up
    optimizers = _optimizers_with_state(model)
    after_warm_up = _object_values(model)
    feed_evidence(model, evidence(share=share), range(20, 40))
    model.auto_choice.after_step(39, optimizers)
    assert model.medium_model == chosen
    expected = initial if chosen == "none" else after_warm_up
    for name, value in _object_values(model).items():
        torch.testing.assert_close(value, expected[name], rtol=0, atol=0, msg=name)
    for group, optimizer in optimizers.optimizers.items():
        restarted = chosen == "none" and group in ("fields", "proposal_networks")
        assert (len(optimizer.state) == 0) == restarted, group
    model.train_step = 40
    # no blend after a restart: clear air at once
    assert model.medium_blend == 1.0 and model.clear_air == (chosen == "none")
    assert model.auto_choice.initial_object is None  # the copy is dropped once decided


def test_after_the_decision_the_medium_blends_to_the_choice_and_the_geometry_holds():
    model = tiny_model(medium_model="auto", medium_first_steps=10, auto_decision_step=40, auto_blend_steps=100)
    feed_evidence(model, evidence(share=0.3, beta_D=(1.2,) * 3, beta_B=(1.2,) * 3, B_inf=(0.6,) * 3), range(20, 40))
    model.auto_choice.after_step(39)
    assert model.medium_model == "fog" and int(model.medium_model_step) == 40
    model.train()
    bundle = rays(24, seed=5)
    learned = model.medium_field(bundle.directions)
    fog = tie(learned, "fog")
    for step, weight in ((40, 0.0), (90, 0.5), (139, 0.99)):
        model.train_step = step
        assert model.medium_blend == pytest.approx(weight)
        out = model(bundle)
        expected = (1 - weight) * learned.sigma_attn + weight * fog.sigma_attn
        torch.testing.assert_close(out["medium_attenuation"], expected.detach(), msg=str(step))
        # the object density gets no gradient while the medium moves; the colour does
        assert not out["accumulation"].requires_grad and not out["expected_depth"].requires_grad
        assert out["clean"].requires_grad
    model.train_step = 140
    out = model(bundle)
    torch.testing.assert_close(out["medium_attenuation"], fog.sigma_attn.detach())
    assert out["accumulation"].requires_grad  # the geometry learns again


def test_the_prior_takes_its_early_weight_up_to_the_medium_fit_and_its_full_weight_after():
    """``research.binary_prior_early_mult`` weighs the prior until ``medium_fit_step`` (throughout
    when there is no fit), then ``binary_prior_mult``; a loaded model (no step) uses the latter."""
    model = tiny_model(medium_model="seathru", medium_first_steps=0, medium_fit_step=50, binary_prior_mult=1e-4, binary_prior_early_mult=1e-3)
    for step, weight in ((0, 1e-3), (49, 1e-3), (50, 1e-4), (None, 1e-4)):
        model.train_step = step
        losses, out, _ = losses_of(model, seed=3)
        expected = weight * binary_transmittance_loss(out["transmittance"], scale=0.1, empty_weight=6.0)
        torch.testing.assert_close(losses["binary_prior_loss"], expected, msg=str(step))
    no_fit = tiny_model(medium_model="seathru", medium_first_steps=0, medium_fit_step=None, binary_prior_early_mult=1e-3)
    assert all(TrainingPhases(no_fit.config, step).binary_prior_weight == 1e-3 for step in (0, 10**6))
    unscheduled = tiny_model(medium_model="seathru", medium_first_steps=0, binary_prior_mult=2e-3, binary_prior_early_mult=None)
    unscheduled.train_step = 0
    losses, out, _ = losses_of(unscheduled, seed=3)
    torch.testing.assert_close(
        losses["binary_prior_loss"], 2e-3 * binary_transmittance_loss(out["transmittance"], scale=0.1, empty_weight=6.0)
    )


def decide_on_sfm_points(seed: int, beta_d, beta_b, warm_up: Optional[MediumEvidence]):
    """A tiny ``auto`` model (first stage 10 steps, deciding at step 40, its medium fit at 40 too)
    whose SfM table holds 200 points in 6 views at ranges 1-3, seen under its own veil through
    ``beta_d``, ``beta_b`` (1/world unit); ``warm_up`` fed as the evidence of steps 20-39, then step
    39's callbacks run (``None``: only those before step 0)."""
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes, TrainingCallbackLocation

    from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY, SFM_OBSERVATIONS_KEY
    from seathru_nerfstudio.data.sfm_observations import SfmObservations
    from seathru_nerfstudio.metadata_keys import EXTENT_KEY

    rng = np.random.default_rng(seed)
    ranges = rng.uniform(1.0, 3.0, (200, 1)) * rng.uniform(0.9, 1.1, (200, 6))
    table = SfmObservations(ranges=ranges, colours=np.zeros((200, 6, 3)))
    model = tiny_model(
        metadata={SCALE_KEY: 1.0, SFM_OBSERVATIONS_KEY: table, EXTENT_KEY: 12.0},
        medium_model="auto", medium_first_steps=10, auto_decision_step=40, medium_fit_step=40,
    )  # fmt: skip
    veil = torch.sigmoid(model.medium_field.rgb_logit.detach().double()).numpy()
    colour = rng.uniform(0.1, 1.0, (200, 1, 3))
    beta_d, beta_b = np.asarray(beta_d), np.asarray(beta_b)
    table.colours[...] = colour * np.exp(-beta_d * ranges[..., None]) + veil * -np.expm1(-beta_b * ranges[..., None])
    callbacks = model.get_training_callbacks(TrainingCallbackAttributes(None, None, None, None))
    if warm_up is None:  # only what runs before the first step
        for callback in callbacks:
            callback.run_callback_at_location(0, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        return model
    feed_evidence(model, warm_up, range(20, 40))
    for callback in callbacks:
        callback.run_callback_at_location(39, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    return model


@pytest.mark.parametrize(
    "warm_up, beta_d, beta_b, chosen",
    [
        # the warm-up looked grey, the SfM points' medium is the water demo's: water it is
        ((1.2,) * 3, (1.3, 1.2, 0.9), (0.95, 0.85, 0.7), "seathru"),
        # the warm-up looked coloured (backscatter at its cap), the points' medium is grey fog
        # whose backscatter density is 0.72 of its attenuation, as fitted on path-traced fog
        ((1.3, 1.2, 0.9), (0.5,) * 3, (0.36,) * 3, "fog"),
    ],
)
def test_auto_decides_from_the_sfm_fit_and_the_fit_then_ties_as_chosen(warm_up, beta_d, beta_b, chosen):
    """At step 40 ``auto`` takes the densities of its evidence from the medium fit to the SfM
    observations, not from the warm-up; the fit that follows in the same step's callbacks
    (``medium_fit_step``) ties as the model chosen, and the densities reach it at the end of their
    move: ``fog`` one grey attenuation and a backscatter density per channel, each the truth."""
    from seathru_nerfstudio.medium_fit import apply_medium_fit

    model = decide_on_sfm_points(1, beta_d, beta_b, evidence(share=0.3, beta_D=warm_up, beta_B=(0.2, 0.1, 0.3), B_inf=(0.6,) * 3))
    assert model.medium_model == chosen
    apply_medium_fit(model, 39 + model.config.research.auto_blend_steps)  # the end of the densities' move to the fit
    sigma = torch.nn.functional.softplus(model.medium_field.density_raw.detach().double())
    torch.testing.assert_close(sigma, torch.from_numpy(np.concatenate([beta_d, beta_b])), rtol=1e-3, atol=0)
    if chosen == "fog":  # tied by the fit: one attenuation, bitwise equal in every channel
        assert torch.equal(sigma[:3], sigma[:1].expand(3))


@pytest.mark.parametrize("medium_density, chosen", [(0.0, "none"), (0.8, "seathru")])
def test_auto_decides_none_from_what_the_fit_explains_at_the_sfm_points(medium_density, chosen):
    """``none`` is decided by how much of the SfM points' colour change the medium fit explains, not
    by the warm-up's backscatter share: the warm-up still shows a share of 0.3 (the object field has
    not yet taken the light the backscatter held), but points whose colour does not change with
    range are clear air; the same points seen through water (coloured densities, as the water demo)
    keep a medium."""
    beta_d = medium_density * np.array([1.3, 1.2, 0.9]) / 0.8
    beta_b = medium_density * np.array([0.95, 0.85, 0.7]) / 0.8
    warm_up = evidence(share=0.3, beta_D=(1.3, 1.2, 0.9), beta_B=(0.95, 0.85, 0.7), B_inf=(0.6,) * 3)
    model = decide_on_sfm_points(3, beta_d, beta_b, warm_up)
    assert model.medium_model == chosen


@pytest.mark.parametrize("medium_density, chosen", [(0.0, "none"), (0.8, "seathru")])
def test_auto_decides_none_before_training_from_the_sfm_points(medium_density, chosen):
    """Where the fit explains too little of the SfM points' colour change, ``auto`` decides ``none``
    before the first step, under the untrained veiling light: no blend, no copy kept to restart
    from, and the run is ``none`` throughout. Points seen through water leave the decision to its
    step (still undecided, rendered as ``seathru``)."""
    beta_d = medium_density * np.array([1.3, 1.2, 0.9]) / 0.8
    beta_b = medium_density * np.array([0.95, 0.85, 0.7]) / 0.8
    model = decide_on_sfm_points(3, beta_d, beta_b, None)
    assert model.medium_model == chosen
    decided = int(model.medium_model_code) != UNDECIDED
    assert decided == (chosen == "none")
    assert int(model.medium_model_step) == -1
    assert (model.auto_choice.initial_object is None) == decided
    assert model.contraction_radius == (1.0 if decided else 12.0)  # clear air: nerfacto's contraction
