"""The backscatter density bounded by the darkest SfM observations (``medium_start``)."""

from __future__ import annotations

import numpy as np
import torch

from seathru_nerfstudio.medium_start import apply_backscatter_cap, backscatter_density_bounds, backscatter_density_cap
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


def test_the_cap_lowers_the_backscatter_at_the_end_of_the_first_stage_only(capsys):
    """The callback acts at the step that ends the first stage: each ``β_B`` above the cap (per metre,
    scene unit × scale) comes down to it, one below stays, ``β_D`` is untouched; other steps, a ray
    medium, clear air (``none``), or no observations change nothing."""
    from seathru_nerfstudio.data.sfm_observations import SfmObservations
    from seathru_nerfstudio.metadata_keys import SCALE_KEY, SFM_OBSERVATIONS_KEY

    rng = np.random.default_rng(2)
    ranges = rng.uniform(1.0, 3.0, (300, 1)) * rng.uniform(0.9, 1.1, (300, 4))
    table = SfmObservations(ranges=ranges, colours=np.zeros((300, 4, 3)))
    metadata = {SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}
    model = tiny_model(metadata=metadata, medium_first_steps=5, medium_fit_step=10)
    veil = torch.sigmoid(model.medium_field.rgb_logit.detach().double()).numpy()
    true_b = np.array([0.2, 5.0, 0.4])  # per metre; the start (per metre) lies between 0.4 and 5.0
    start = torch.nn.functional.softplus(model.medium_field.density_raw.detach().double()) * 2.0
    assert float(start[4]) < 5.0 and float(start[5]) > 0.4
    albedo = rng.uniform(0.0, 0.5, (300, 1, 3)) ** 3
    table.colours[...] = albedo * np.exp(-ranges[..., None]) + veil * -np.expm1(-true_b * ranges[..., None])
    before = model.medium_field.density_raw.detach().clone()
    apply_backscatter_cap(model, 3)
    assert torch.equal(model.medium_field.density_raw.detach(), before)
    apply_backscatter_cap(model, 4)
    after = torch.nn.functional.softplus(model.medium_field.density_raw.detach().double()) * 2.0
    assert torch.equal(model.medium_field.density_raw.detach()[:3], before[:3])
    assert float(after[4]) == float(start[4])  # below its cap: stays
    for channel in (3, 5):  # capped near the black surfaces' density
        assert true_b[channel - 3] <= float(after[channel]) < min(float(start[channel]), 1.5 * true_b[channel - 3])
    assert "capped" in capsys.readouterr().out
    ray = tiny_model(metadata=metadata, medium_first_steps=5, medium_fit_step=10, medium_scope="ray")
    state = {k: v.clone() for k, v in ray.state_dict().items()}
    apply_backscatter_cap(ray, 4)
    assert all(torch.equal(state[k], v) for k, v in ray.state_dict().items())
    clear = tiny_model(metadata=metadata, medium_first_steps=5, medium_fit_step=10, medium_model="none")
    clear_before = clear.medium_field.density_raw.detach().clone()
    apply_backscatter_cap(clear, 4)
    assert torch.equal(clear.medium_field.density_raw.detach(), clear_before)
    bare = tiny_model(metadata={SCALE_KEY: 2.0}, medium_first_steps=5, medium_fit_step=10)
    bare_before = bare.medium_field.density_raw.detach().clone()
    apply_backscatter_cap(bare, 4)
    assert torch.equal(bare.medium_field.density_raw.detach(), bare_before)
