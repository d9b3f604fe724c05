"""The scene medium's veiling light: constant at and below the horizon, rising towards the surface."""

from __future__ import annotations

import pytest
import torch

from seathru_nerfstudio.medium_field import SceneMedium


def _unit(vectors: torch.Tensor) -> torch.Tensor:
    return vectors / vectors.norm(dim=-1, keepdim=True)


def _medium(rise: list[float]) -> SceneMedium:
    medium = SceneMedium(init_density=0.3, init_rgb=[0.1, 0.3, 0.6])
    with torch.no_grad():
        medium.rgb_rise.copy_(torch.tensor(rise))
    return medium


def test_the_veil_is_the_same_in_every_direction_before_it_rises():
    directions = _unit(torch.randn(64, 3, generator=torch.Generator().manual_seed(0)))
    veil = SceneMedium(init_rgb=[0.1, 0.3, 0.6])(directions).rgb
    assert torch.allclose(veil, torch.tensor([0.1, 0.3, 0.6]).expand(64, 3), atol=1e-6)


def test_below_the_horizon_the_veil_is_the_horizontal_one_whatever_the_rise():
    medium = _medium([2.0, -1.0, 3.0])
    downward = _unit(torch.tensor([[1.0, 0.0, -0.5], [0.0, 1.0, -3.0], [0.3, -0.2, 0.0], [0.0, 0.0, -1.0]]))
    veil = medium(downward).rgb
    assert torch.allclose(veil, medium.horizontal_veil().detach().expand(4, 3), atol=1e-6)


def test_above_the_horizon_the_veil_is_the_logistic_of_the_rise_times_the_up_component():
    medium = _medium([2.0, -1.0, 3.0])
    directions = _unit(torch.tensor([[1.0, 0.0, 0.5], [0.0, 0.2, 1.0], [0.0, 0.0, 1.0]]))
    expected = torch.sigmoid(torch.logit(torch.tensor([0.1, 0.3, 0.6])) + directions[:, 2:3] * torch.tensor([2.0, -1.0, 3.0]))
    assert torch.allclose(medium(directions).rgb, expected, atol=1e-6)


def test_the_rise_learns_only_from_rays_that_look_up():
    medium = _medium([0.0, 0.0, 0.0])
    downward = _unit(torch.tensor([[1.0, 0.0, -0.2], [0.0, 1.0, 0.0]]))
    medium(downward).rgb.sum().backward()
    assert medium.rgb_rise.grad.abs().max() == 0 and medium.rgb_logit.grad.abs().min() > 0
    medium.zero_grad()
    medium(_unit(torch.tensor([[1.0, 0.0, 0.4]]))).rgb.sum().backward()
    assert medium.rgb_rise.grad.abs().min() > 0


def test_a_checkpoint_without_the_rise_loads_with_a_veil_the_same_everywhere():
    old = {"rgb_logit": torch.logit(torch.tensor([0.2, 0.4, 0.5])), "density_raw": torch.zeros(6)}
    medium = _medium([1.0, 1.0, 1.0])
    medium.load_state_dict(old)
    assert torch.equal(medium.rgb_rise.detach(), torch.zeros(3))
    up = medium(torch.tensor([[0.0, 0.0, 1.0]])).rgb
    assert torch.allclose(up, torch.tensor([[0.2, 0.4, 0.5]]), atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_extreme_rises_stay_finite_and_in_range_in_half_precision(dtype):
    medium = _medium([1e4, -1e4, 60.0])
    directions = _unit(torch.randn(32, 3, generator=torch.Generator().manual_seed(1))).to(dtype)
    veil = medium(directions).rgb
    assert torch.isfinite(veil).all() and (veil >= 0).all() and (veil <= 1).all()
