"""The densities at entry, bounded by the darkest and brightest SfM observations (``medium_start``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seathru_nerfstudio.medium_start import (
    CLEAREST_QUANTILE,
    LEAST_CLEAREST,
    OPEN_SHARE,
    OpenWaterColour,
    is_open_water,
    apply_density_caps,
    attenuation_bounds,
    attenuation_cap,
    backscatter_density_bounds,
    backscatter_density_cap,
)
from tiny_training import tiny_model


def test_a_black_surface_bounds_the_density_at_its_true_value_and_a_lit_one_above():
    """``I = B∞ (1 - e^{-β_B z})`` (``J = 0``) gives back ``β_B``; ``J > 0`` a larger bound; ``I >= B∞``
    or a zero veil no bound (``inf``); ``I <= 0`` the bound 0; all finite or ``inf``, never NaN."""
    veil = torch.tensor([0.05, 0.2, 0.4], dtype=torch.float64)
    beta_b = torch.tensor([0.3, 0.15, 0.08], dtype=torch.float64)
    z = torch.tensor([0.5, 2.0, 7.0, 30.0], dtype=torch.float64)
    black = veil * -torch.expm1(-beta_b * z[:, None])
    torch.testing.assert_close(backscatter_density_bounds(z, black, veil), beta_b.expand(4, 3), rtol=1e-12, atol=0)
    lit = black + 0.01 * torch.exp(-beta_b * z[:, None])
    assert (backscatter_density_bounds(z, lit, veil) > beta_b).all()
    edge = torch.tensor([[0.05, 0.3, -0.1], [1e-30, 0.2, 0.0]], dtype=torch.float64)
    bounds = backscatter_density_bounds(torch.tensor([1.0, 1.0], dtype=torch.float64), edge, veil)
    assert torch.isinf(bounds[0, :2]).all() and bounds[0, 2] == 0 and bounds[1, 2] == 0
    assert torch.isinf(bounds[1, 1]) and torch.isfinite(bounds[1, 0])
    zero_veil = backscatter_density_bounds(z[:1], black[:1], torch.zeros(3, dtype=torch.float64))
    assert torch.isinf(zero_veil).all()
    half = backscatter_density_bounds(z[:1], torch.full((1, 3), 0.5, dtype=torch.float32), torch.ones(3)).to(torch.float64)
    torch.testing.assert_close(half, torch.full((1, 3), np.log(2.0) / 0.5, dtype=torch.float64), rtol=1e-6, atol=0)


def test_the_cap_is_the_darkest_percent_of_the_bounds_and_skips_unusable_observations():
    """On a scene whose surfaces range from black to bright, the 1% cap lies between the true density
    (the black ones) and the lit ones' bounds; NaN or non-positive ranges are left out; no usable
    observation bounds nothing."""
    rng = np.random.default_rng(0)
    veil = torch.tensor([0.05, 0.2, 0.4], dtype=torch.float64)
    beta_b, beta_d = torch.tensor([0.3, 0.15, 0.08], dtype=torch.float64), torch.tensor([0.35, 0.2, 0.1], dtype=torch.float64)
    n = 4000
    z = torch.from_numpy(rng.uniform(1.5, 12.0, n))
    albedo = torch.from_numpy(rng.uniform(0.0, 0.6, (n, 3)) ** 2)  # a few near-black surfaces at every range
    colours = albedo * torch.exp(-beta_d * z[:, None]) + veil * -torch.expm1(-beta_b * z[:, None])
    cap = backscatter_density_cap(z, colours, veil)
    assert (cap >= beta_b).all() and (cap < backscatter_density_bounds(z, colours, veil).median(dim=0).values).all()
    assert (cap < 1.5 * beta_b).all()  # the darkest 1% are near black: the cap is near the truth
    spoiled = z.clone()
    spoiled[:10] = float("nan")
    spoiled[10:20] = -1.0
    dark = colours.clone()
    dark[:20] = 0.0  # these would set the cap at 0 if they counted
    torch.testing.assert_close(backscatter_density_cap(spoiled, dark, veil), backscatter_density_cap(z[20:], colours[20:], veil))
    assert torch.isinf(backscatter_density_cap(spoiled[:20], dark[:20], veil)).all()


def test_a_white_surface_bounds_the_attenuation_at_its_true_value_and_a_darker_one_above():
    """``I = e^{-β_D z} + B∞ (1 - e^{-β_B z})`` (``J = 1``) gives back ``β_D``; ``J < 1`` a larger bound;
    ``I`` at or below the backscatter no bound (``inf``); 1 or more left above it the bound 0; never NaN."""
    veil = torch.tensor([0.05, 0.2, 0.4], dtype=torch.float64)
    beta_b, beta_d = torch.tensor([0.3, 0.15, 0.08], dtype=torch.float64), torch.tensor([0.35, 0.2, 0.1], dtype=torch.float64)
    z = torch.tensor([0.5, 2.0, 7.0, 30.0], dtype=torch.float64)
    backscatter = veil * -torch.expm1(-beta_b * z[:, None])
    white = torch.exp(-beta_d * z[:, None]) + backscatter
    torch.testing.assert_close(attenuation_bounds(z, white, veil, beta_b), beta_d.expand(4, 3), rtol=1e-10, atol=0)
    grey = 0.5 * torch.exp(-beta_d * z[:, None]) + backscatter
    torch.testing.assert_close(attenuation_bounds(z, grey, veil, beta_b), beta_d + np.log(2.0) / z[:, None], rtol=1e-10, atol=0)
    edge = torch.stack([backscatter[1], backscatter[1] - 0.01, backscatter[1] + 1.0, backscatter[1] + 2.0])
    bounds = attenuation_bounds(torch.full((4,), 2.0, dtype=torch.float64), edge, veil, beta_b)
    assert torch.isinf(bounds[:2]).all() and (bounds[2:] >= 0).all() and (bounds[2:] < 1e-12).all()  # 0 up to rounding
    half = attenuation_bounds(z[:1], torch.full((1, 3), 0.5, dtype=torch.float32), torch.zeros(3), torch.zeros(3))
    torch.testing.assert_close(half.to(torch.float64), torch.full((1, 3), np.log(2.0) / 0.5, dtype=torch.float64), rtol=1e-6, atol=0)


def test_the_attenuation_cap_is_the_brightest_percent_and_lies_at_or_above_the_truth():
    """Surfaces from black to white at every range: the 1% cap lies at or above the true ``β_D`` (a white
    surface reaches it exactly) and below the median bound; unusable observations are left out."""
    rng = np.random.default_rng(1)
    veil = torch.tensor([0.05, 0.2, 0.4], dtype=torch.float64)
    beta_b, beta_d = torch.tensor([0.3, 0.15, 0.08], dtype=torch.float64), torch.tensor([0.35, 0.2, 0.1], dtype=torch.float64)
    n = 4000
    z = torch.from_numpy(rng.uniform(1.5, 12.0, n))
    albedo = torch.from_numpy(1.0 - rng.uniform(0.0, 1.0, (n, 3)) ** 2)  # a few near-white surfaces at every range
    colours = albedo * torch.exp(-beta_d * z[:, None]) + veil * -torch.expm1(-beta_b * z[:, None])
    cap = attenuation_cap(z, colours, veil, beta_b)
    assert (cap >= beta_d).all() and (cap < 1.1 * beta_d).all()
    assert (cap < attenuation_bounds(z, colours, veil, beta_b).median(dim=0).values).all()
    spoiled = z.clone()
    spoiled[:10] = float("nan")
    bright = colours.clone()
    bright[:10] = 1.0  # these would set the cap at 0 if they counted
    torch.testing.assert_close(attenuation_cap(spoiled, bright, veil, beta_b), attenuation_cap(z[10:], colours[10:], veil, beta_b))
    assert torch.isinf(attenuation_cap(spoiled[:10], bright[:10], veil, beta_b)).all()


def test_the_caps_lower_the_densities_at_the_end_of_the_first_stage_only(capsys):
    """The callback acts at the step that ends the first stage: each density above its cap (per
    metre, scene unit × scale) comes down to it, near its truth, one below stays; other steps, a ray
    medium, clear air (``none``), or no observations change nothing."""
    from seathru_nerfstudio.data.sfm_observations import SfmObservations
    from seathru_nerfstudio.metadata_keys import SCALE_KEY, SFM_OBSERVATIONS_KEY

    rng = np.random.default_rng(2)
    ranges = rng.uniform(1.0, 3.0, (300, 1)) * rng.uniform(0.9, 1.1, (300, 4))
    table = SfmObservations(ranges=ranges, colours=np.zeros((300, 4, 3)))
    metadata = {SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}
    model = tiny_model(metadata=metadata, medium_first_steps=5, medium_fit_step=10)
    veil = torch.sigmoid(model.medium_field.rgb_logit.detach().double()).numpy()
    true_d, true_b = np.array([0.3, 5.0, 0.6]), np.array([0.2, 5.0, 0.4])  # per metre, either side of the start
    start = torch.nn.functional.softplus(model.medium_field.density_raw.detach().double()) * 2.0
    assert (start[[0, 2, 3, 5]] > 0.6).all() and (start[[1, 4]] < 5.0).all()
    spread = rng.uniform(0.0, 1.0, (300, 1, 3)) ** 3 / 2
    albedo = np.where(rng.uniform(0.0, 1.0, (300, 1, 3)) < 0.5, spread, 1.0 - spread)  # near black and near white
    table.colours[...] = albedo * np.exp(-true_d * ranges[..., None]) + veil * -np.expm1(-true_b * ranges[..., None])
    before = model.medium_field.density_raw.detach().clone()
    apply_density_caps(model, 3)
    assert torch.equal(model.medium_field.density_raw.detach(), before)
    apply_density_caps(model, 4)
    after = torch.nn.functional.softplus(model.medium_field.density_raw.detach().double()) * 2.0
    truth = np.concatenate([true_d, true_b])
    for index in (1, 4):  # below its cap: stays
        assert float(after[index]) == float(start[index])
    for index in (0, 2, 3, 5):  # capped near the white (attenuation) or black (backscatter) surfaces' density
        assert truth[index] <= float(after[index]) < min(float(start[index]), 1.5 * truth[index]), (index, after)
    assert "bounded" in capsys.readouterr().out
    ray = tiny_model(metadata=metadata, medium_first_steps=5, medium_fit_step=10, medium_scope="ray")
    state = {k: v.clone() for k, v in ray.state_dict().items()}
    apply_density_caps(ray, 4)
    assert all(torch.equal(state[k], v) for k, v in ray.state_dict().items())
    clear = tiny_model(metadata=metadata, medium_first_steps=5, medium_fit_step=10, medium_model="none")
    clear_before = clear.medium_field.density_raw.detach().clone()
    apply_density_caps(clear, 4)
    assert torch.equal(clear.medium_field.density_raw.detach(), clear_before)
    bare = tiny_model(metadata={SCALE_KEY: 2.0}, medium_first_steps=5, medium_fit_step=10)
    bare_before = bare.medium_field.density_raw.detach().clone()
    apply_density_caps(bare, 4)
    assert torch.equal(bare.medium_field.density_raw.detach(), bare_before)


def test_the_open_water_colour_is_the_mean_of_the_rays_the_geometry_leaves_open():
    """Only rays open past :data:`OPEN_SHARE` count (a half-open silhouette ray does not), over every
    batch added; under 1% of the rays open, or none, there is no estimate."""
    water = torch.tensor([0.07, 0.2, 0.39])
    estimate = OpenWaterColour()
    assert estimate.mean() is None
    colours = torch.stack([water, water + 0.02, torch.tensor([0.9, 0.1, 0.1]), torch.tensor([0.3, 0.3, 0.3])])
    shares = torch.tensor([[1.0], [OPEN_SHARE + 1e-3], [OPEN_SHARE - 1e-3], [0.5]])
    estimate.add(colours, shares, torch.zeros(4, 1))
    estimate.add(colours[:1], shares[:1], torch.zeros(1, 1))
    torch.testing.assert_close(estimate.mean(), ((2 * water + water + 0.02) / 3).double(), rtol=1e-6, atol=1e-7)
    assert (estimate.open_rays, estimate.rays) == (3, 5)
    sparse = OpenWaterColour()
    sparse.add(water.expand(1000, 3), torch.cat([torch.ones(9, 1), torch.zeros(991, 1)]), torch.zeros(1000, 1))
    assert sparse.mean() is None  # 0.9% open
    sparse.add(water.expand(2, 3), torch.ones(2, 1), torch.zeros(2, 1))
    torch.testing.assert_close(sparse.mean(), water.double())


def test_open_rays_are_judged_against_the_clearest_rays_of_their_batch():
    """A haze on every ray (all open shares scaled by 0.9) leaves the same rays open; the threshold is
    :data:`OPEN_SHARE` of the batch's clearest ray (the 99th percentile, an actual share), so a ray just
    above it counts and one just below does not; with no clear ray in view (every share at most 0.5)
    nothing counts, since the clearest are taken to pass at least :data:`LEAST_CLEAREST`; an empty
    batch has no open ray."""
    generator = torch.Generator().manual_seed(0)
    shares = torch.cat([torch.rand(300, generator=generator) * 0.5, 0.97 + 0.03 * torch.rand(200, generator=generator)])
    clear = is_open_water(shares)
    assert int(clear.sum()) == 200 and bool(clear[300:].all())
    assert torch.equal(is_open_water(0.9 * shares), clear)
    assert int((0.9 * shares > OPEN_SHARE).sum()) == 0  # a fixed threshold would count none of them
    level = torch.cat([shares[:300], torch.full((200,), 0.98)])  # the clearest: 0.98 whatever is added below it
    assert float(torch.quantile(level, CLEAREST_QUANTILE, interpolation="higher")) == pytest.approx(0.98)
    edge = torch.cat([level, OPEN_SHARE * 0.98 + torch.tensor([1e-4, -1e-4])])
    assert is_open_water(edge)[-2:].tolist() == [True, False]
    closed = torch.rand(1000, generator=generator) * 0.5
    assert not bool(is_open_water(closed).any())
    assert int(is_open_water(torch.cat([closed, torch.full((20,), OPEN_SHARE * LEAST_CLEAREST + 1e-3)])).sum()) == 20
    assert is_open_water(torch.zeros(0)).shape == (0,)


def test_the_veil_becomes_the_open_water_colour_at_the_end_of_the_first_stage(capsys):
    """The callback at the first stage's last step sets the scene medium's veil to the estimate and
    says so; before that step, or with no estimate, the veil is unchanged."""
    model = tiny_model(medium_first_steps=5, medium_fit_step=10)
    water = torch.tensor([0.07, 0.2, 0.39])
    model.open_water_colour.add(water.expand(10, 3), torch.ones(10, 1), torch.zeros(10, 1))
    before = torch.sigmoid(model.medium_field.rgb_logit).detach().clone()
    apply_density_caps(model, 3)
    torch.testing.assert_close(torch.sigmoid(model.medium_field.rgb_logit).detach(), before)
    apply_density_caps(model, 4)
    torch.testing.assert_close(torch.sigmoid(model.medium_field.rgb_logit).detach(), water, rtol=1e-5, atol=1e-6)
    assert "the colour of 10 open rays" in capsys.readouterr().out
    none_open = tiny_model(medium_first_steps=5, medium_fit_step=10)
    before = torch.sigmoid(none_open.medium_field.rgb_logit).detach().clone()
    apply_density_caps(none_open, 4)
    torch.testing.assert_close(torch.sigmoid(none_open.medium_field.rgb_logit).detach(), before)


def test_the_open_water_rise_is_the_line_of_the_open_rays_above_the_level():
    """Open rays above the level plane whose colour is linear in ``up``, and below it a flat colour
    (far seabed the first stage has not formed): the slope is the line above the level, exactly,
    whatever the rays below; the veil starts where that line passes the mean colour (per channel, not
    below the mean elevation), follows the line up to the highest open ray and stays there; a channel
    that darkens looking up has no rise. Without open rays above the level the line is that of all
    the open rays, from their mean elevation; a level view has no slope."""
    from seathru_nerfstudio.medium_field import SceneMedium

    up_above = torch.linspace(0.01, 0.4, 200)[:, None]
    slope = torch.tensor([0.1, 0.3, -0.2])
    intercept = torch.tensor([0.05, 0.2, 0.4])
    above = intercept + up_above * slope
    up_below = torch.linspace(-0.2, 0.0, 300)[:, None]
    below = torch.tensor([0.07, 0.26, 0.3]).expand(300, 3)
    estimate = OpenWaterColour()
    estimate.add(below, torch.ones(300, 1), up_below)
    estimate.add(above[:50], torch.ones(50, 1), up_above[:50])
    estimate.add(above[50:], torch.ones(150, 1), up_above[50:])
    start, fitted, highest = estimate.rise()
    torch.testing.assert_close(fitted, slope.double(), rtol=1e-4, atol=1e-5)
    # the line itself, through the mean of the rays above the level: at the level ray it is the intercept
    up_mean, colour_mean, line_slope = estimate.line_above_level()
    assert up_mean == pytest.approx(float(up_above.double().mean()), rel=1e-6)
    assert torch.equal(line_slope, fitted)
    torch.testing.assert_close(colour_mean - line_slope * up_mean, intercept.double(), rtol=1e-4, atol=1e-5)
    mean, mean_up = estimate.mean(), float(torch.cat([up_below, up_above]).double().mean())
    crossing = (mean - intercept.double()) / slope.double()
    expected_start = torch.where(slope > 0, crossing.clamp(min=mean_up), torch.full((3,), mean_up, dtype=torch.float64))
    torch.testing.assert_close(start, expected_start, rtol=1e-4, atol=1e-5)
    assert highest == pytest.approx(0.4, abs=1e-6)

    medium = SceneMedium(init_rgb=mean.tolist())
    medium.set_veil_rise(start, (fitted.clamp_min(0) / mean).float(), highest)
    directions = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, -1.0], [1.0, 0.0, 0.3], [1.0, 0.0, 1.0]]), dim=-1)
    veil = medium(directions).rgb.double()
    seen = directions[:, 2:3].double().clamp(max=highest)  # above the highest open ray the veil stays at its value there
    expected = mean + fitted.clamp_min(0) * (seen - start).clamp_min(0)
    torch.testing.assert_close(veil, expected, rtol=1e-5, atol=1e-6)
    on_line = (intercept + float(seen[1]) * slope).double()
    follows = (slope > 0) & (crossing >= mean_up)  # the rising channels whose line passes the mean above the mean elevation
    assert bool(follows.any())
    torch.testing.assert_close(veil[1][follows], on_line[follows], rtol=1e-4, atol=1e-5)
    assert torch.all(veil[2] >= veil[1]) and torch.all(veil[1] >= veil[0])
    assert torch.isfinite(medium(directions.half()).rgb).all()

    downward = OpenWaterColour()
    up = torch.linspace(-0.4, -0.01, 300)[:, None]
    downward.add(intercept + up * slope, torch.ones(300, 1), up)
    start, fitted, _ = downward.rise()
    torch.testing.assert_close(fitted, slope.double(), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(start, torch.full((3,), float(up.double().mean()), dtype=torch.float64), rtol=1e-5, atol=1e-6)
    level = OpenWaterColour()
    level.add(above, torch.ones(200, 1), torch.zeros(200, 1))
    assert torch.equal(level.rise()[1], torch.zeros(3, dtype=torch.float64))
    assert downward.line_above_level() is None and level.line_above_level() is None  # no ray looks up


def test_the_open_waters_change_round_the_horizon_is_read_with_the_elevation_as_a_covariate():
    """Open rays above the level whose colour is a plane in ``(up, h1, h2)``, the elevation rising with
    ``h1`` (a rig that looks up more on one side): :meth:`OpenWaterColour.across` gives the plane's
    slopes along ``h`` exactly (the line over ``up`` alone would not separate them), the rays' mean
    ``h`` and their extent; rays below the level count for nothing. All rays looking one way round the
    horizon give no change."""
    generator = torch.Generator().manual_seed(3)
    azimuth = torch.rand(400, generator=generator) * 1.2 - 0.6
    up = (0.05 + 0.2 * torch.rand(400, generator=generator) + 0.1 * azimuth).clamp(0.01, 0.6)
    level = torch.stack([torch.sin(azimuth), torch.cos(azimuth)], dim=1) * torch.sqrt(1 - up**2)[:, None]
    slope_up = torch.tensor([0.1, 0.3, 0.5])
    slope_level = torch.tensor([[0.02, 0.05, 0.08], [-0.01, 0.0, 0.03]])
    colours = torch.tensor([0.05, 0.2, 0.4]) + up[:, None] * slope_up + level @ slope_level
    up = up[:, None]
    estimate = OpenWaterColour()
    estimate.add(colours[:100], torch.ones(100, 1), up[:100], level[:100])
    estimate.add(colours[100:], torch.ones(300, 1), up[100:], level[100:])
    estimate.add(torch.ones(50, 3), torch.ones(50, 1), torch.full((50, 1), -0.2), torch.full((50, 2), 0.99))
    mean, slope, low, high = estimate.across()
    torch.testing.assert_close(slope, slope_level.double(), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(mean, level.double().mean(dim=0), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(low, level.double().amin(dim=0), rtol=0, atol=1e-6)
    torch.testing.assert_close(high, level.double().amax(dim=0), rtol=0, atol=1e-6)

    one_way = OpenWaterColour()
    one_way.add(colours, torch.ones(400, 1), up, torch.tensor([[0.0, 1.0]]).expand(400, 2))
    assert one_way.line_above_level() is not None and one_way.across() is None


def test_the_open_water_sums_are_in_the_checkpoint_so_a_resumed_first_stage_reads_the_same_veil(tmp_path):
    """A model whose first stage was killed after some batches and loaded from its checkpoint
    (``torch.save``, then the safe loader ns-train uses) holds the same sums; the batches it then
    adds give the veil an uninterrupted stage gives, to the last bit. A checkpoint written before
    the sums were saved loads with none (``strict=False``, as nerfstudio falls back to)."""
    from seathru_nerfstudio.compat import load_checkpoint

    up = torch.linspace(-0.3, 0.5, 40)[:, None]
    colours = torch.tensor([0.05, 0.2, 0.4]) + up * torch.tensor([0.02, 0.1, 0.05]) + 0.01 * torch.rand(40, 3)
    shares = torch.where(torch.arange(40)[:, None] % 3 == 0, 0.2, 1.0)  # a third of the rays closed
    whole = tiny_model(medium_first_steps=6, medium_fit_step=10)
    killed = tiny_model(medium_first_steps=6, medium_fit_step=10)
    for model in (whole, killed):
        model.open_water_colour.add(colours[:25], shares[:25], up[:25])
    torch.save({"pipeline": killed.state_dict()}, tmp_path / "step.ckpt")
    state = load_checkpoint(tmp_path / "step.ckpt")["pipeline"]
    assert "open_water_colour._extra_state" in state
    resumed = tiny_model(medium_first_steps=6, medium_fit_step=10)
    resumed.load_state_dict(state)
    for model in (whole, resumed):
        model.open_water_colour.add(colours[25:], shares[25:], up[25:])
    assert (resumed.open_water_colour.open_rays, resumed.open_water_colour.rays) == (whole.open_water_colour.open_rays, 40)
    for model in (whole, resumed):
        apply_density_caps(model, 5)  # the first stage's last step: the veil and its rise are read
    assert torch.equal(resumed.medium_field.rgb_logit, whole.medium_field.rgb_logit)
    assert torch.equal(resumed.medium_field.state_dict()["veil_rise"], whole.medium_field.state_dict()["veil_rise"])
    older = {k: v for k, v in state.items() if not k.startswith("open_water_colour.")}
    fresh = tiny_model(medium_first_steps=6, medium_fit_step=10)
    assert fresh.load_state_dict(older, strict=False).missing_keys == ["open_water_colour._extra_state"]
    assert fresh.open_water_colour.rays == 0 and fresh.open_water_colour.mean() is None
    before_above = state["open_water_colour._extra_state"][:11]  # a checkpoint from before the sums above the level
    fresh.open_water_colour.set_extra_state(before_above)
    assert fresh.open_water_colour.open_rays == killed.open_water_colour.open_rays
    assert not fresh.open_water_colour.above_gram.any() and not fresh.open_water_colour.above_colour.any()
    # A checkpoint from before the level components: its 9 sums above the level (count, colour, up colour,
    # up, up^2) give the same line, and no change round the horizon.
    read = killed.open_water_colour
    gram, colour = read.above_gram, read.above_colour
    before_level = torch.cat([
        state["open_water_colour._extra_state"][:11], gram[0, :1], colour[0], colour[1], gram[0, 1:2], gram[1, 1:2],
    ])
    fresh.open_water_colour.set_extra_state(before_level)
    for got, want in zip(fresh.open_water_colour.line_above_level(), read.line_above_level()):
        torch.testing.assert_close(torch.as_tensor(got), torch.as_tensor(want), rtol=1e-12, atol=0.0)
    assert fresh.open_water_colour.across() is None
