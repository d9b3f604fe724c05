"""The veiling light read from the open water and held from the medium fit on (issue 36)."""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.engine.callbacks import TrainingCallbackAttributes, TrainingCallbackLocation

from seathru_nerfstudio.open_water_veil import OpenWaterVeil

from test_model import rays
from tiny_training import tiny_model


def test_the_estimate_is_the_decayed_open_share_weighted_mean():
    """Three batches, then the closed form ``Σ d^age Σ T I / Σ d^age Σ T`` with ``d = 1 - 1/window``."""
    g = torch.Generator().manual_seed(0)
    veil = OpenWaterVeil(window=4.0)
    batches = [(torch.rand(50, 1, generator=g), torch.rand(50, 3, generator=g)) for _ in range(3)]
    for share, colour in batches:
        veil.update(share, colour)
    d = 0.75
    ages = (2, 1, 0)
    numerator = sum(d**a * (s.double() * c.double()).sum(0) for a, (s, c) in zip(ages, batches))
    denominator = sum(d**a * s.double().sum() for a, (s, _) in zip(ages, batches))
    torch.testing.assert_close(veil.estimate(), numerator / denominator, rtol=1e-12, atol=0)


def test_rays_that_end_on_matter_do_not_count_and_open_rays_give_their_colour():
    """Object rays (open share 0) of any colour leave the estimate at the open water's colour."""
    water = torch.tensor([0.05, 0.24, 0.47])
    veil = OpenWaterVeil()
    for step in range(5):
        objects = torch.rand(100, 3, generator=torch.Generator().manual_seed(step))
        shares = torch.cat([torch.zeros(100, 1), torch.ones(20, 1)])
        veil.update(shares, torch.cat([objects, water.expand(20, 3)]))
    torch.testing.assert_close(veil.estimate(), water.double(), rtol=1e-12, atol=0)


def test_without_open_water_there_is_no_estimate():
    """No ray, or fewer than ``min_open_share`` of the rays more than half open: ``None``; at the
    share itself, an estimate."""
    assert OpenWaterVeil().estimate() is None
    faint = OpenWaterVeil(min_open_share=0.01)
    faint.update(torch.full((1000, 1), 0.4), torch.rand(1000, 3))  # a little light through every object ray
    assert faint.estimate() is None
    enough = OpenWaterVeil(min_open_share=0.01)
    enough.update(torch.cat([torch.full((990, 1), 0.4), torch.ones(10, 1)]), torch.rand(1000, 3))
    assert enough.estimate() is not None
    with pytest.raises(ValueError, match="window"):
        OpenWaterVeil(window=1.0)


def test_extreme_and_non_finite_inputs_stay_finite():
    """Shares outside [0, 1] are clamped, non-finite colours count as absent, huge colours stay finite."""
    veil = OpenWaterVeil()
    colours = torch.tensor([[float("nan"), 0.0, 0.0], [float("inf"), 1.0, 1.0], [1e30, 1e30, 1e30], [0.2, 0.3, 0.4]])
    veil.update(torch.tensor([[1.0], [1.0], [-5.0], [7.0]]), colours)
    torch.testing.assert_close(veil.estimate(), torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64))
    assert bool(torch.isfinite(veil.colour_sum).all())


def fit_step_callbacks(model, step: int) -> None:
    for callback in model.get_training_callbacks(TrainingCallbackAttributes(None, None, None, None)):
        callback.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)


def train_batch(model, step: int, image: torch.Tensor) -> dict:
    model.train()
    model.train_step = step
    out = model(rays(image.shape[0], seed=step))
    batch = {"image": image}
    return model.get_loss_dict(out, batch, model.get_metrics_dict(out, batch))


def test_the_model_reads_the_open_water_between_the_first_stage_and_the_fit_and_then_holds_it():
    """Batches of the first stage (every ray shows the veil) and after the fit add nothing; at the
    fit the veil becomes the estimate, is checkpointed, and gets no gradient from then on."""
    model = tiny_model(medium_model="seathru", medium_first_steps=2, medium_fit_step=6)
    image = torch.full((32, 3), 0.3)
    for step in range(2):
        train_batch(model, step, image)
    assert float(model.open_water_veil.ray_count) == 0.0
    for step in range(2, 6):
        train_batch(model, step, image)
    assert float(model.open_water_veil.ray_count) > 0.0
    model.open_water_veil.colour_sum.mul_(0.0).add_(torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
    model.open_water_veil.open_sum.fill_(1.0)
    model.open_water_veil.half_open_count.copy_(model.open_water_veil.ray_count)
    fit_step_callbacks(model, 5)  # the fit at the end of step 5 (no SfM table: the densities train on)
    assert bool(model.veil_held)
    torch.testing.assert_close(torch.sigmoid(model.medium_field.rgb_logit.detach().double()), torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64), rtol=1e-6, atol=0)
    state = model.state_dict()
    assert bool(state["veil_held"]) and "open_water_veil.colour_sum" in state
    counted = float(model.open_water_veil.ray_count)
    losses = train_batch(model, 6, image)
    assert float(model.open_water_veil.ray_count) == counted
    sum(losses.values()).backward()
    grad = model.medium_field.rgb_logit.grad
    assert grad is None or bool((grad == 0).all())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.field.parameters())


def test_without_open_water_the_learned_veil_stays_and_trains_on():
    model = tiny_model(medium_model="seathru", medium_first_steps=0, medium_fit_step=3)
    before = model.medium_field.rgb_logit.detach().clone()
    fit_step_callbacks(model, 2)
    assert not bool(model.veil_held)
    assert torch.equal(model.medium_field.rgb_logit.detach(), before)
    losses = train_batch(model, 3, torch.full((16, 3), 0.3))
    sum(losses.values()).backward()
    assert model.medium_field.rgb_logit.grad is not None and math.isfinite(float(model.medium_field.rgb_logit.grad.abs().sum()))
