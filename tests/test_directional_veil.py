"""A scene medium's veiling light depends on the ray direction: ``c_med(d) = sigmoid(a + W d)``
(``SceneMedium``), and the SfM fit and the entry caps read each observation's own veil."""

from __future__ import annotations

import numpy as np
import torch

from seathru_nerfstudio.data.sfm_observations import SfmObservations
from seathru_nerfstudio.medium_field import SceneMedium, observed_veil
from seathru_nerfstudio.medium_fit import fit_densities

BETA_D = torch.tensor([0.3, 0.17, 0.12], dtype=torch.float64)
BETA_B = torch.tensor([0.3, 0.14, 0.08], dtype=torch.float64)
LOGIT = torch.tensor([-3.0, -1.3, -0.2], dtype=torch.float64)
SLOPE = torch.tensor([[0.0, 0.0, 0.0], [0.4, 0.8, 1.2], [0.0, 0.0, 0.0]], dtype=torch.float64)
"""Brighter looking up (+y), most in blue: the shape of path-traced coastal water's open water."""


def medium_with_slope() -> SceneMedium:
    medium = SceneMedium(init_density=0.5, init_rgb=0.5)
    with torch.no_grad():
        medium.rgb_logit.copy_(LOGIT)
        medium.rgb_direction.copy_(SLOPE)
    return medium


def test_the_veil_is_the_sigmoid_of_a_logit_linear_in_the_direction_and_starts_constant():
    directions = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    fresh = SceneMedium(init_rgb=(0.1, 0.2, 0.4))
    torch.testing.assert_close(fresh(directions.float()).rgb, torch.tensor([0.1, 0.2, 0.4]).expand(50, 3))
    medium = medium_with_slope()
    expected = torch.sigmoid(LOGIT + directions @ SLOPE)
    torch.testing.assert_close(medium.veil(directions), expected, rtol=1e-6, atol=0)
    torch.testing.assert_close(medium(directions.float()).rgb, expected.float(), rtol=1e-6, atol=1e-7)
    extreme = medium.veil(torch.tensor([[0.0, 1e30, 0.0], [0.0, -1e30, 0.0]], dtype=torch.float64))
    assert torch.isfinite(extreme).all() and (extreme >= 0).all() and (extreme <= 1).all()
    # the veil's gradient reaches W (the medium's optimiser group holds it)
    medium(directions.float()).rgb.sum().backward()
    assert medium.rgb_direction.grad is not None and medium.rgb_direction.grad.abs().sum() > 0


def test_a_checkpoint_from_before_the_directional_veil_loads_with_a_constant_one():
    old = {k: v for k, v in medium_with_slope().state_dict().items() if k != "rgb_direction"}
    medium = SceneMedium()
    medium.load_state_dict(old)
    assert torch.equal(medium.rgb_direction.detach(), torch.zeros(3, 3))
    torch.testing.assert_close(medium.rgb_logit.detach().double(), LOGIT)


def test_observation_directions_point_from_the_camera_to_the_point():
    points = np.array([[0.0, 0.0, -2.0], [1.0, 1.0, 0.0]])
    centres = np.array([[0.0, 0.0, 0.0], [1.0, 3.0, 0.0]])
    table = SfmObservations(np.ones((2, 2)), np.zeros((2, 2, 3)), points=points, centres=centres)
    directions = table.directions()
    np.testing.assert_allclose(directions[0, 0], [0, 0, -1])
    np.testing.assert_allclose(directions[1, 1], [0, -1, 0])
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0)
    assert SfmObservations(np.ones((2, 2)), np.zeros((2, 2, 3))).directions() is None


def test_the_fit_under_each_observations_own_veil_recovers_the_medium_and_one_constant_veil_does_not():
    """Points seen from views above and beside them (lines of sight from 40 degrees down to level):
    the formation model with the direction's veil. Fitted under each observation's veil the
    densities come back; under the veil of the mean direction they come back several times worse
    (the robust fit's weights take up part of the difference)."""
    rng = np.random.default_rng(0)
    num_points, num_views = 400, 8
    points = rng.uniform(-2.0, 2.0, (num_points, 3)) * np.array([1.0, 0.2, 1.0])
    angles = rng.uniform(0.0, 2 * np.pi, num_views)
    heights = rng.uniform(0.0, 4.0, num_views)
    centres = np.stack([6 * np.cos(angles), heights, 6 * np.sin(angles)], axis=-1)
    ranges = np.linalg.norm(points[:, None] - centres[None], axis=-1)
    table = SfmObservations(ranges, np.zeros((num_points, num_views, 3)), points=points, centres=centres)
    medium = medium_with_slope()
    veil = observed_veil(medium, torch.from_numpy(table.directions()))
    z = torch.from_numpy(ranges)[..., None]
    albedo = torch.from_numpy(rng.uniform(0.05, 0.9, (num_points, 1, 3)))
    colours = albedo * torch.exp(-BETA_D * z) + veil * -torch.expm1(-BETA_B * z)
    start = torch.full((3,), 0.5, dtype=torch.float64)
    fit = fit_densities(torch.from_numpy(ranges), colours, veil, start, start)
    torch.testing.assert_close(fit.attenuation, BETA_D, rtol=0.02, atol=0)
    torch.testing.assert_close(fit.backscatter, BETA_B, rtol=0.02, atol=0)
    constant = observed_veil(medium, torch.from_numpy(table.directions()).mean(dim=(0, 1)))
    wrong = fit_densities(torch.from_numpy(ranges), colours, constant, start, start)

    def worst_error(result) -> float:  # the largest relative error over the six densities
        found, truth = torch.cat([result.attenuation, result.backscatter]), torch.cat([BETA_D, BETA_B])
        return float(((found - truth).abs() / truth).max())

    assert worst_error(wrong) > 3 * worst_error(fit)
    assert observed_veil(medium, None).shape == (3,)
