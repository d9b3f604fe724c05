"""The SfM observation table and the densities fitted to it: closed forms and constructed scenes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seathru_nerfstudio.data.sfm_observations import at_flattest_pixels, sfm_observations
from seathru_nerfstudio.medium_fit import (
    DensityFit,
    fit_replaces,
    explained_variation,
    CAUCHY_TUNING,
    MAD_TO_SIGMA,
    best_colours,
    cauchy_weights,
    fit_densities,
    newton_polished,
    veil_sensitivity,
)
from seathru_nerfstudio.medium_fit_errors import LOG_DENSITY_LIMIT, log_density_errors, tied_log_density_errors
from seathru_nerfstudio.medium_field import MEDIUM_MODELS, MediumOutputs, tie, tie_matrix

BETA_D = torch.tensor([1.3, 1.2, 0.9], dtype=torch.float64)
BETA_B = torch.tensor([0.95, 0.85, 0.7], dtype=torch.float64)
VEIL = torch.tensor([0.07, 0.2, 0.39], dtype=torch.float64)


def _observations(num_points=300, num_views=8, seed=0):
    """Points with colours in [0.1, 1] seen at ranges 1-3 m (each point's own spread of 10%), some unobserved."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(1.0, 3.0, (num_points, 1))
    ranges = torch.tensor(base * rng.uniform(0.9, 1.1, (num_points, num_views)))
    colour = torch.tensor(rng.uniform(0.1, 1.0, (num_points, 3)))
    images = colour[:, None, :] * torch.exp(-BETA_D * ranges[..., None]) + VEIL * -torch.expm1(-BETA_B * ranges[..., None])
    hidden = torch.tensor(rng.uniform(size=(num_points, num_views)) < 0.3)
    ranges[hidden] = float("nan")
    images[hidden] = float("nan")
    return ranges, images, colour


def test_the_best_colour_is_the_true_one_under_the_true_medium():
    ranges, images, colour = _observations()
    observed = torch.isfinite(ranges).double()
    z = torch.nan_to_num(ranges)
    best, predicted = best_colours(z, torch.nan_to_num(images), observed, BETA_D, BETA_B, VEIL)
    torch.testing.assert_close(best, colour)
    torch.testing.assert_close(predicted[observed.bool()], images[observed.bool()])


def test_the_fit_recovers_the_medium_from_either_side():
    ranges, images, _ = _observations()
    for start in (0.5, 2.5):
        s = torch.full((3,), start, dtype=torch.float64)
        beta_d, beta_b, residual, _, _ = fit_densities(ranges, images, VEIL, s, s)
        torch.testing.assert_close(beta_d, BETA_D, rtol=0.02, atol=0)
        torch.testing.assert_close(beta_b, BETA_B, rtol=0.05, atol=0)
        assert residual < 1e-9


def test_a_wrong_veil_moves_the_fit_and_extreme_inputs_stay_finite():
    ranges, images, _ = _observations()
    s = torch.full((3,), 1.0, dtype=torch.float64)
    beta_d, _, residual, _, _ = fit_densities(ranges, images, VEIL * 1.3, s, s)
    assert residual > 1e-7 and not torch.allclose(beta_d, BETA_D, rtol=0.02)
    huge = torch.full((2, 3), 1e30, dtype=torch.float64)
    fit = fit_densities(huge, torch.ones(2, 3, 3, dtype=torch.float64), VEIL, s, s, max_iterations=5)
    assert all(torch.isfinite(v).all() for v in (fit.attenuation, fit.backscatter, fit.attenuation_log_error, fit.backscatter_log_error))
    assert np.isfinite(fit.residual)
    with pytest.raises(ValueError, match="positive"):
        fit_densities(ranges, images, VEIL, -s, s)
    with pytest.raises(ValueError, match="no observations"):
        fit_densities(torch.full((2, 3), float("nan")), torch.zeros(2, 3, 3), VEIL, s, s)


def test_cauchy_weights_halve_at_the_tuning_residual_and_vanish_far_beyond():
    """``1 / (1 + (r / (c s))²)`` with ``s = 1.4826 median r``: the median residual weighs
    ``1 / (1 + (1 / (1.4826 c))²)``, twice the scale's ``c`` ½, unobserved 0; exact data keep
    their exact observations at 1 and drop the rest; huge residuals stay finite (weight 0)."""
    r = torch.tensor([[0.1, 0.2, 0.3], [0.2, 0.2, 5.0]], dtype=torch.float64)
    observed = torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 0.0]], dtype=torch.float64)
    w = cauchy_weights(r, observed)
    scale = MAD_TO_SIGMA * 0.2  # the median of the five observed residuals
    torch.testing.assert_close(w[0, 1], torch.tensor(1 / (1 + (0.2 / (CAUCHY_TUNING * scale)) ** 2), dtype=torch.float64))
    assert w[1, 2] == 0.0 and torch.all(w[observed > 0] > 0) and w[0, 0] > w[0, 1] > w[0, 2]
    half = cauchy_weights(torch.tensor([[0.2, 0.2, CAUCHY_TUNING * scale]], dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64))
    torch.testing.assert_close(half[0, 2], torch.tensor(0.5, dtype=torch.float64))
    exact = cauchy_weights(torch.tensor([[0.0, 0.0, 0.0, 0.3]], dtype=torch.float64), torch.ones(1, 4, dtype=torch.float64))
    assert exact[0, :3].eq(1.0).all() and exact[0, 3] < 1e-20
    huge = cauchy_weights(torch.tensor([[1e300, 1.0, 1.0]], dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64))
    assert torch.isfinite(huge).all() and huge[0, 0] == 0.0
    assert cauchy_weights(r, torch.zeros_like(r)).eq(0).all()  # nothing observed: no median, no NaN


def test_the_robust_fit_ignores_views_that_see_the_water_behind_a_silhouette():
    """One point in eight is an edge: in a third of its views its colour is half the water
    behind it (``B∞ (1 - e^{-β_B (z + 4)})``), as a bilinear sample across a silhouette is. Least
    squares (``reweightings=0``) lets those pull β_B off; the Cauchy rounds bring all six back.
    On Gaussian noise the two fits agree."""
    ranges, images, _ = _observations(num_points=400)
    rng = np.random.default_rng(1)
    mixed = torch.tensor((rng.uniform(size=ranges.shape) < 1 / 3) & (np.arange(400)[:, None] % 8 == 0)) & torch.isfinite(ranges)
    water = VEIL * -torch.expm1(-BETA_B * (ranges[..., None] + 4.0))
    edged = torch.where(mixed[..., None], 0.5 * images + 0.5 * water, images)
    s = torch.full((3,), 1.0, dtype=torch.float64)
    plain = fit_densities(ranges, edged, VEIL, s, s, reweightings=0)
    robust = fit_densities(ranges, edged, VEIL, s, s)
    truth = torch.cat([BETA_D, BETA_B])
    plain_error = (torch.cat([plain.attenuation, plain.backscatter]) / truth - 1).abs()
    robust_error = (torch.cat([robust.attenuation, robust.backscatter]) / truth - 1).abs()
    assert plain_error.max() > 0.1, plain_error  # the contamination matters...
    assert robust_error.max() < 0.03, robust_error  # ...and the reweighting removes it
    assert robust.residual < plain.residual
    # on Gaussian noise alone the reweighting costs little: it stays within a quarter of the
    # least-squares fit's own standard error of it
    noisy = images + 0.005 * torch.randn(images.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    squares, cauchy = fit_densities(ranges, noisy, VEIL, s, s, reweightings=0), fit_densities(ranges, noisy, VEIL, s, s)
    for a, b, error in ((squares.attenuation, cauchy.attenuation, squares.attenuation_log_error), (squares.backscatter, cauchy.backscatter, squares.backscatter_log_error)):
        assert torch.all((a.log() - b.log()).abs() < 0.25 * error), (a, b, error)
    with pytest.raises(ValueError, match="reweightings"):
        fit_densities(ranges, edged, VEIL, s, s, reweightings=-1)


SIZE, F, C = 20, 20.0, 10.0


def _camera_at(x: float, z: float) -> np.ndarray:
    c2w = np.zeros((3, 4))
    c2w[:, :3] = np.eye(3)
    c2w[0, 3], c2w[2, 3] = x, z
    return c2w


def test_the_table_holds_true_ranges_and_colours_and_leaves_out_hidden_views():
    """A wall at z = -4 seen by three cameras looking along -z; the third has a near screen at
    z = -1 in front of it (its own sparse map sees the screen), so the wall is hidden there."""
    cams = [_camera_at(0.0, 0.0), _camera_at(0.5, 1.0), _camera_at(-0.3, 0.5)]
    wall_depth = [4.0, 5.0, 4.5]  # z-depth of the wall from each camera
    depths, images = [], []
    for i, cam in enumerate(cams):
        depth = np.zeros((SIZE, SIZE))
        depth[2:18:3, 2:18:3] = wall_depth[i]
        if i == 2:
            depth[:, :] = 0.0
            depth[1:19:2, 1:19:2] = 1.5  # the screen, 1 m in front of this camera's wall points
        depths.append(depth)
        images.append(np.full((SIZE, SIZE, 3), 0.1 * (i + 1)))
    table = sfm_observations(depths, images, np.stack(cams), *(np.full(3, v) for v in (F, F, C, C)))
    assert table.num_points > 0
    assert np.all(np.isnan(table.ranges[:, 2]))  # hidden behind the screen from the third view
    seen = np.isfinite(table.ranges)
    assert seen[:, 0].any() and seen[:, 1].any()
    # every wall point: range from camera j = distance to the camera centre; colour = that image's value
    for j in (0, 1):
        rows = seen[:, j]
        np.testing.assert_allclose(table.colours[rows, j], 0.1 * (j + 1))
        assert np.all(table.ranges[rows, j] >= wall_depth[j] - 1e-9)
    with pytest.raises(ValueError, match="max_points_per_view"):
        sfm_observations(depths, images, np.stack(cams), *(np.full(3, v) for v in (F, F, C, C)), max_points_per_view=0)
    # many views: fewer points from each (here 6 in all over 3 views, 2 from each, at most)
    capped = sfm_observations(depths, images, np.stack(cams), *(np.full(3, v) for v in (F, F, C, C)), max_points=6)
    assert 0 < capped.num_points <= 6 < table.num_points
    with pytest.raises(ValueError, match="max_points"):
        sfm_observations(depths, images, np.stack(cams), *(np.full(3, v) for v in (F, F, C, C)), max_points=0)


def test_points_move_at_their_depth_to_the_flattest_pixel_within_reach():
    """``at_flattest_pixels``: a point moves, keeping its z-depth, to the pixel of least gradient
    within the window, only where that is strictly flatter; ties go to the nearest; nothing
    outside the image or the window counts, and on a uniform image (or ``within`` 0) nothing moves."""
    rng = np.random.default_rng(0)
    image = rng.uniform(0.0, 1.0, (12, 12, 3))  # textured everywhere
    image[3:6, 7:10] = 0.5  # a flat patch: zero gradient at its centre (4, 8)
    depth = np.zeros((12, 12))
    depth[4, 6] = 1.7  # two columns from the patch's centre
    depth[10, 1] = 2.5  # far from it
    moved = at_flattest_pixels(depth, image, within=2)
    assert moved[4, 8] == 1.7 and moved[4, 6] == 0.0
    grey = image.mean(axis=-1)
    texture = np.hypot(*np.gradient(grey))
    window = texture[8:12, 0:4]  # (10, 1)'s window, clipped by the image
    row, col = np.unravel_index(np.argmin(window), window.shape)
    assert moved[8 + row, col] == 2.5 and np.count_nonzero(moved) == 2
    np.testing.assert_array_equal(at_flattest_pixels(depth, image, within=0), depth)
    np.testing.assert_array_equal(at_flattest_pixels(depth, np.full((12, 12, 3), 0.3), within=2), depth)
    # equally flat pixels at one and two pixels: the nearer wins
    ramp = np.tile(np.arange(12.0)[None, :, None] ** 2, (12, 1, 3)) / 144  # gradient grows with the column
    ramp[6, 4] = ramp[6, 6] = 0.2  # zero gradient at (6, 5), one pixel from the point at (6, 6)...
    ramp[6, 7] = ramp[6, 9] = 0.7  # ...and at (6, 8), two pixels from it
    assert np.hypot(*np.gradient(ramp.mean(axis=-1)))[6, [5, 8]].max() == 0.0
    at = np.zeros((12, 12))
    at[6, 6] = 1.0
    assert at_flattest_pixels(at, ramp, within=2)[6, 5] == 1.0
    with pytest.raises(ValueError, match="flattest_within"):
        sfm_observations([depth], [image], np.eye(4)[None, :3], *(np.ones(1) for _ in range(4)), flattest_within=-1)


def test_on_a_rendered_scene_the_fit_finds_the_attenuation_the_start_missed(tmp_path):
    """seathru-synth water (64x48, 12 views), the dataparser's table, the true veiling light: every
    channel's attenuation ends within 30% of the truth, from a start 46-111% above it. (On the 160x120
    demo, 2026-11-26, bdb49e1: within 9%.)"""
    import json

    from seathru_nerfstudio.data.nerfstudio_data import SFM_OBSERVATIONS_KEY, SeathruNerfstudioDataParserConfig
    from seathru_nerfstudio.data.synthetic import SynthConfig, generate

    scene = generate(SynthConfig(output_dir=tmp_path / "water", width=64, height=48, num_views=12, supersample=1, sfm_points_per_view=150))
    truth = json.loads((scene / "ground_truth" / "medium.json").read_text())
    parser = SeathruNerfstudioDataParserConfig(data=scene).setup()
    table = parser.get_dataparser_outputs("train").metadata[SFM_OBSERVATIONS_KEY]
    assert table.num_points > 500 and table.num_observations > 4 * table.num_points
    start = torch.full((3,), 1.9, dtype=torch.float64)
    beta_d = fit_densities(torch.from_numpy(table.ranges), torch.from_numpy(table.colours), torch.tensor(truth["B_inf"]), start, start).attenuation
    error = (beta_d / torch.tensor(truth["beta_D"]) - 1).abs()
    assert torch.all(error < 0.3), (beta_d, truth["beta_D"])
    # the table is the dataparser's default; without it there is none
    plain = SeathruNerfstudioDataParserConfig(data=scene, sfm_observations=False).setup().get_dataparser_outputs("train").metadata
    assert SFM_OBSERVATIONS_KEY not in plain


def test_a_channel_without_information_stays_finite_and_bounded():
    """Black points under a black veil: nothing constrains the densities, and nothing may leave the bounds."""
    ranges = torch.tensor([[1.0, 2.0], [1.5, 3.0]], dtype=torch.float64)
    black = torch.zeros(2, 2, 3, dtype=torch.float64)
    for start in (1e-12, 1.0, 1e12):
        s = torch.full((3,), start, dtype=torch.float64)
        beta_d, beta_b, residual, error_d, error_b = fit_densities(ranges, black, torch.zeros(3, dtype=torch.float64), s, s)
        assert torch.all(error_d == 2 * LOG_DENSITY_LIMIT) and torch.all(error_b == 2 * LOG_DENSITY_LIMIT)  # flat: no information
        for beta in (beta_d, beta_b):
            assert torch.isfinite(beta).all() and torch.all(beta > 0)
            assert torch.all(beta.log().abs() <= LOG_DENSITY_LIMIT + 1e-9)
        assert residual == 0.0


def test_the_newton_polish_reaches_the_minimum_and_leaves_flat_directions_alone():
    """``e^{x₀} - x₀ + (x₁ - 2)² + 0·x₂``: the minimum is ``x₀ = 0, x₁ = 2``; ``x₂`` is flat (no
    curvature) and keeps its start; a loss that is NaN everywhere leaves the start unchanged."""
    loss = lambda x: torch.exp(x[0]) - x[0] + (x[1] - 2.0) ** 2 + 0.0 * x[2]  # noqa: E731
    start = torch.tensor([1.5, -3.0, 7.0], dtype=torch.float64)
    polished = newton_polished(loss, start)
    assert abs(float(polished[0])) < 1e-12 and abs(float(polished[1]) - 2.0) < 1e-12
    assert polished[2] == start[2]
    assert torch.equal(newton_polished(lambda x: x.sum() * float("nan"), start), start)


def test_the_standard_errors_follow_gauss_newton():
    """``cov_c = 2 S_c / num_points · H_c⁻¹`` on a hand-made curvature: channel 0 has
    ``H = [[4, 1], [1, 2]]`` (inverse diagonal 2/7, 4/7), channel 1 a flat direction (the largest
    error), channel 2 a diagonal ``H``."""
    hessian = torch.zeros(6, 6, dtype=torch.float64)
    hessian[0, 0], hessian[3, 3], hessian[0, 3], hessian[3, 0] = 4.0, 2.0, 1.0, 1.0
    hessian[1, 1], hessian[4, 4], hessian[1, 4], hessian[4, 1] = 1.0, 1.0, 1.0, 1.0  # singular
    hessian[2, 2], hessian[5, 5] = 8.0, 0.5
    squared = torch.tensor([0.7, 1.0, 0.2], dtype=torch.float64)
    error_d, error_b = log_density_errors(squared, hessian, num_points=10)
    torch.testing.assert_close(error_d[0], torch.sqrt(torch.tensor(2 * 0.07 * 2 / 7, dtype=torch.float64)))
    torch.testing.assert_close(error_b[0], torch.sqrt(torch.tensor(2 * 0.07 * 4 / 7, dtype=torch.float64)))
    assert error_d[1] == error_b[1] == 2 * LOG_DENSITY_LIMIT
    torch.testing.assert_close(error_d[2], torch.sqrt(torch.tensor(2 * 0.02 / 8, dtype=torch.float64)))
    torch.testing.assert_close(error_b[2], torch.sqrt(torch.tensor(2 * 0.02 / 0.5, dtype=torch.float64)))
    assert torch.all(log_density_errors(squared, hessian, num_points=0)[0] == 2 * LOG_DENSITY_LIMIT)


def test_the_errors_shrink_with_more_points_and_grow_without_range_spread():
    """Noisy observations: twice the points (the same ones again, in another order) give the same
    densities and errors smaller by exactly √2 (the mean residual and the weights are unchanged;
    the residual sum, the curvature and the number of points all double: no degrees-of-freedom
    correction); the spread of the fit over noise draws is within the predicted error; points that
    keep one range in every view leave β_D undetermined.

    In another order the sums round differently: before the Newton polish, L-BFGS stopped where
    that rounding decided, and the error moved by up to 8.5%."""
    ranges, images, _ = _observations(num_points=400)
    s = torch.full((3,), 1.0, dtype=torch.float64)
    fits = []
    for seed in range(8):
        noise = 0.01 * torch.randn(images.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        fits.append(fit_densities(ranges, (images + noise).clamp(min=0), VEIL, s, s))
    fit = fits[0]
    noisy = (images + 0.01 * torch.randn(images.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)).clamp(min=0)
    order = torch.randperm(800, generator=torch.Generator().manual_seed(0))
    doubled = fit_densities(torch.cat([ranges, ranges])[order], torch.cat([noisy, noisy])[order], VEIL, s, s)
    for same, single in ((doubled.attenuation, fit.attenuation), (doubled.backscatter, fit.backscatter)):
        torch.testing.assert_close(same, single, rtol=1e-9, atol=0)
    torch.testing.assert_close(doubled.attenuation_log_error * 2**0.5, fit.attenuation_log_error, rtol=1e-8, atol=0)
    torch.testing.assert_close(doubled.backscatter_log_error * 2**0.5, fit.backscatter_log_error, rtol=1e-8, atol=0)
    spread = torch.stack([f.attenuation.log() for f in fits]).std(dim=0)
    assert torch.all(spread < fit.attenuation_log_error), (spread, fit.attenuation_log_error)
    assert torch.all(spread > fit.attenuation_log_error / 10)  # conservative (views share a point's error), not vacuous
    flat = torch.nan_to_num(ranges, nan=0.0)[:, :1].expand_as(ranges).clone()
    flat[torch.isnan(ranges)] = float("nan")
    one_range = fit_densities(flat, images, VEIL, s, s)
    assert torch.all(one_range.attenuation_log_error > 10 * fit.attenuation_log_error), one_range.attenuation_log_error


def test_beta_b_follows_the_veil_one_for_one_at_short_range_and_more_as_the_backscatter_saturates():
    """Near the camera the backscatter is ``B∞ β_B z``: the observations fix the product, so a veil
    ``k`` times too bright gives ``β_B / k``, ``d ln β_B / d ln B∞ = −1`` up to terms of order
    ``β_B z``. Farther, where the backscatter saturates, no ``β_B`` makes up for a veil error one for
    one (a single range needs ``−(e^x − 1) / x``, ``x = β_B z``): the sensitivity grows with the range."""
    ranges, _, colour = _observations()
    s = torch.full((3,), 1.0, dtype=torch.float64)
    sensitivities = []
    for scale in (0.02, 0.1, 1.0):  # ranges 0.018-0.066, 0.09-0.33 and 0.9-3.3 world units
        near = ranges * scale
        images = _images_under(near, colour, BETA_D, BETA_B)
        fit = fit_densities(near, images, VEIL, s, s)
        sensitivities.append(veil_sensitivity(near, images, VEIL, fit))
    shortest = sensitivities[0]
    largest_x = BETA_B * torch.nan_to_num(ranges * 0.02, nan=0.0).max()
    assert torch.all((shortest + 1).abs() < largest_x), (shortest, largest_x)
    assert torch.all(sensitivities[0] > sensitivities[1]) and torch.all(sensitivities[1] > sensitivities[2]), sensitivities
    nearest_x = BETA_B * torch.nan_to_num(ranges, nan=float("inf")).min()  # x at the nearest observation
    assert torch.all(sensitivities[2] < -torch.expm1(nearest_x) / nearest_x), sensitivities[2]  # past a single range's
    near = ranges * 0.02  # fog keeps β_B per channel: on fog (grey attenuation), each channel meets the limit −1
    near_images = _images_under(near, colour, BETA_D.mean().expand(3), BETA_B)
    fog = fit_densities(near, near_images, VEIL, s, s, tie="fog")
    tied = veil_sensitivity(near, near_images, VEIL, fog, tie="fog")
    assert torch.isfinite(tied).all() and torch.all((tied + 1).abs() < largest_x), (tied, largest_x)
    assert len(torch.unique(tied)) == 3  # one per channel, not one grey value


def _images_under(ranges, colour, beta_d, beta_b):
    return colour[:, None, :] * torch.exp(-beta_d * ranges[..., None]) + VEIL * -torch.expm1(-beta_b * ranges[..., None])


def test_a_tied_fit_recovers_a_tied_medium_and_keeps_its_densities_equal():
    """``fog``: one grey attenuation and a backscatter density per channel (the light that scatters
    has a colour of its own); ``uniform``: attenuation = backscatter per channel."""
    ranges, _, colour = _observations()
    s_d, s_b = torch.tensor([2.0, 1.5, 0.6], dtype=torch.float64), torch.tensor([0.8, 1.1, 1.7], dtype=torch.float64)
    grey, coloured_backscatter = torch.full((3,), 1.2, dtype=torch.float64), torch.tensor([0.95, 0.85, 0.7], dtype=torch.float64)
    fog = fit_densities(ranges, _images_under(ranges, colour, grey, coloured_backscatter), VEIL, s_d, s_b, tie="fog")
    torch.testing.assert_close(fog.attenuation, grey, rtol=1e-4, atol=0)
    torch.testing.assert_close(fog.backscatter, coloured_backscatter, rtol=1e-4, atol=0)
    assert torch.equal(fog.attenuation, fog.attenuation[:1].expand(3))
    per_channel = torch.tensor([1.3, 1.0, 0.7], dtype=torch.float64)
    uniform = fit_densities(ranges, _images_under(ranges, colour, per_channel, per_channel), VEIL, s_d, s_b, tie="uniform")
    torch.testing.assert_close(uniform.attenuation, per_channel, rtol=1e-4, atol=0)
    assert torch.equal(uniform.attenuation, uniform.backscatter)
    # water is not grey: tied, the fit cannot reach it, and says so through its residual
    water = _images_under(ranges, colour, BETA_D, BETA_B)
    assert fit_densities(ranges, water, VEIL, s_d, s_b, tie="fog").residual > 100 * fit_densities(ranges, water, VEIL, s_d, s_b).residual + 1e-12
    with pytest.raises(ValueError, match="tie"):
        tie_matrix("final")


@pytest.mark.parametrize("model", MEDIUM_MODELS[1:])
def test_every_model_is_fitted_as_it_renders(model):
    """The fit's densities are a fixed point of the rendering's tie, for every medium model: the
    fit and the renderer read one table (``basic`` ties as ``uniform``, with no mapping)."""
    ranges, _, colour = _observations()
    water = _images_under(ranges, colour, BETA_D, BETA_B)
    start = torch.tensor([2.0, 1.5, 0.6], dtype=torch.float64), torch.tensor([0.8, 1.1, 1.7], dtype=torch.float64)
    fit = fit_densities(ranges, water, VEIL, *start, tie=model)
    fitted = MediumOutputs(rgb=VEIL, sigma_attn=fit.attenuation, sigma_bs=fit.backscatter)
    rendered = tie(fitted, model)
    torch.testing.assert_close(rendered.sigma_attn, fit.attenuation, rtol=1e-12, atol=0)
    torch.testing.assert_close(rendered.sigma_bs, fit.backscatter, rtol=1e-12, atol=0)
    free = len(torch.unique(torch.cat([fit.attenuation, fit.backscatter])))
    assert free == tie_matrix(model).shape[1]  # water is not grey: each free density takes its own value


def test_tied_errors_add_the_channels_information_and_reduce_to_the_block_formula():
    """Untied (the identity), the tied formula is :func:`log_density_errors` block by block. Tied to one
    parameter with the same curvature in every channel, the information adds up: the error is the
    single-channel error over √3; the six densities share it."""
    blocks = [torch.tensor([[4.0, 1.0], [1.0, 2.0]]), torch.tensor([[3.0, -0.5], [-0.5, 1.0]]), torch.tensor([[8.0, 0.0], [0.0, 0.5]])]
    squared = torch.tensor([0.7, 0.3, 0.2], dtype=torch.float64)
    channel_hessians = torch.zeros(3, 6, 6, dtype=torch.float64)
    for c, block in enumerate(blocks):
        channel_hessians[c][[[c], [c + 3]], [c, c + 3]] = block.double()
    block_errors = log_density_errors(squared, channel_hessians.sum(dim=0), num_points=10)
    tied_errors = tied_log_density_errors(squared, channel_hessians, tie_matrix("seathru"), num_points=10)
    for block_error, tied_error in zip(block_errors, tied_errors):
        torch.testing.assert_close(tied_error, block_error)
    one = torch.full((3, 1, 1), 5.0, dtype=torch.float64)
    same = torch.full((3,), 0.4, dtype=torch.float64)
    all_six = torch.ones(6, 1, dtype=torch.float64)  # the paper's fog: one density for all six
    error_d, error_b = tied_log_density_errors(same, one, all_six, num_points=10)
    single = torch.sqrt(torch.tensor(2 * 0.04 / 5.0, dtype=torch.float64))
    torch.testing.assert_close(error_d, (single / 3**0.5).expand(3))
    assert torch.equal(error_d, error_b)
    flat = torch.zeros(3, 1, 1, dtype=torch.float64)  # no curvature: undetermined
    assert torch.all(tied_log_density_errors(same, flat, all_six, num_points=10)[0] == 2 * LOG_DENSITY_LIMIT)


def test_bilinear_is_exact_on_a_plane_and_clamps_at_the_outermost_centres():
    """On an image that is a plane in pixel coordinates (a colour per channel) bilinear interpolation
    is exact between the pixel centres; beyond the outermost centres it holds their value; a 2-D
    image works as a 3-D one."""
    from seathru_nerfstudio.data.sfm_observations import bilinear

    rows, cols = np.mgrid[0:5, 0:7]
    plane = np.stack([1.0 + 0.5 * cols + 0.25 * rows, 2.0 - 0.1 * cols, 0.3 * rows], axis=-1)  # at pixel centres
    u, v = np.array([0.5, 3.7, 6.5, 2.25]), np.array([0.5, 1.2, 4.5, 3.9])
    x, y = u - 0.5, v - 0.5
    expected = np.stack([1.0 + 0.5 * x + 0.25 * y, 2.0 - 0.1 * x, 0.3 * y], axis=-1)
    np.testing.assert_allclose(bilinear(plane, u, v), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(bilinear(plane[..., 0], u, v), expected[:, 0], rtol=0, atol=1e-12)
    outside = bilinear(plane, np.array([-3.0, 40.0]), np.array([-1.0, 20.0]))
    np.testing.assert_allclose(outside, plane[[0, 4], [0, 6]], rtol=0, atol=1e-12)


def test_the_explained_variation_is_the_medium_s_share_of_the_colour_change_between_views():
    """``1 - Σ (I - J a - B)² / Σ (I - Ī_p)²`` over the observed entries: 1 on colours the medium
    drew (an unobserved entry, NaN, changes nothing); by hand on one point whose colour the medium
    predicts only in part; 0 without a medium; 0, not NaN, where no colour changes."""
    nan = float("nan")
    rng = np.random.default_rng(4)
    veil = torch.tensor([0.1, 0.3, 0.5], dtype=torch.float64)
    beta_d, beta_b = torch.tensor([0.6, 0.4, 0.3], dtype=torch.float64), torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64)
    ranges = torch.from_numpy(rng.uniform(1.0, 4.0, (30, 4)))
    colour = torch.from_numpy(rng.uniform(0.1, 0.9, (30, 1, 3)))
    drawn = colour * torch.exp(-beta_d * ranges[..., None]) + veil * -torch.expm1(-beta_b * ranges[..., None])
    ranges[0, 1], drawn[0, 1] = nan, nan
    torch.testing.assert_close(explained_variation(ranges, drawn, veil, beta_d, beta_b), torch.ones(3, dtype=torch.float64))
    zero = torch.zeros(3, dtype=torch.float64)
    torch.testing.assert_close(explained_variation(ranges, drawn, veil, zero, zero), zero)
    still = colour.expand(30, 4, 3).clone()
    torch.testing.assert_close(explained_variation(ranges, still, veil, beta_d, beta_b), zero)
    # a medium that fits worse than none explains nothing (unclamped: -7.5, -48, -181), nor does one
    # on a change of 1e-155 whose square underflows (unclamped: about -5e300)
    wrong = explained_variation(ranges, drawn, veil, 20 * beta_d, 0.01 * beta_b)
    torch.testing.assert_close(wrong, zero)
    barely = still.clone()
    barely[:, 0] += 1e-155
    assert torch.equal(explained_variation(ranges, barely, veil, beta_d, beta_b), zero)

    # one point at ranges 1 and 2, only attenuation 1 /world unit: a = e^-1, e^-2
    z = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    seen = torch.tensor([[[0.5, 0.5, 0.5], [0.1, 0.1, 0.1]]], dtype=torch.float64)
    a = torch.exp(-torch.tensor([1.0, 2.0], dtype=torch.float64))
    j = float((a * torch.tensor([0.5, 0.1], dtype=torch.float64)).sum() / (a**2).sum())
    left = float(((torch.tensor([0.5, 0.1], dtype=torch.float64) - j * a) ** 2).sum())
    expected = torch.full((3,), 1.0 - left / (2 * 0.2**2), dtype=torch.float64)
    torch.testing.assert_close(explained_variation(z, seen, veil, torch.ones(3, dtype=torch.float64), zero), expected)


def test_the_fit_replaces_where_it_is_precise_whatever_the_trained_attenuation():
    """``fit_replaces``: a channel is replaced where the fit's standard error of ``ln β_D`` is at
    most the bound, at the bound included; the decision reads only the fit, so two runs with other
    trained values decide alike; a non-finite error replaces nothing."""
    fitted = torch.tensor([0.25, 0.14, 0.08], dtype=torch.float64)
    error = torch.tensor([0.05, 0.2, 0.3], dtype=torch.float64)
    fit = DensityFit(fitted, fitted, 0.0, error, error)
    assert fit_replaces(fit, 0.1).tolist() == [True, False, False]
    assert fit_replaces(fit, 0.2).tolist() == [True, True, False]  # the bound itself replaces
    assert fit_replaces(fit, 0.35).tolist() == [True, True, True]
    assert not fit_replaces(fit, 0.01).any()
    blind = DensityFit(fitted, fitted, 0.0, torch.tensor([float("nan"), float("inf"), 0.2], dtype=torch.float64), error)
    assert fit_replaces(blind, 1e300).tolist() == [False, False, True]
