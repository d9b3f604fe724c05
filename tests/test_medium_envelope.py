"""The dark-envelope backscatter estimate on observations drawn from the formation model."""

from __future__ import annotations

import numpy as np
import pytest

from seathru_nerfstudio.medium_envelope import dark_envelope, fit_envelope

VEIL = np.array([0.1, 0.3, 0.4])
BETA_B = np.array([0.4, 0.25, 0.2])
BETA_D = np.array([0.6, 0.3, 0.2])


def observations(veil, beta_b, beta_d, n=20000, seed=0):
    rng = np.random.default_rng(seed)
    z = rng.uniform(1.0, 10.0, n)
    clean = rng.uniform(0.0, 1.0, (n, 3)) ** 2  # many dark surfaces, as on a reef
    return z, clean * np.exp(-beta_d * z[:, None]) + veil * -np.expm1(-beta_b * z[:, None])


@pytest.mark.parametrize("known_veil", [False, True])
def test_the_envelope_recovers_the_backscatter_of_formula_drawn_water(known_veil):
    z, image = observations(VEIL, BETA_B, BETA_D)
    centres, dark = dark_envelope(z, image)
    fit = fit_envelope(centres, dark, VEIL if known_veil else None)
    truth = VEIL * -np.expm1(-BETA_B * centres[:, None])
    # the dark surfaces' own light sits on top of the backscatter: the fit separates it to within a
    # few per cent of the veil at every range, far below the backscatter itself
    assert np.abs(fit.backscatter(centres) - truth).max() < 0.05 * VEIL.max()
    assert np.all(np.diff(centres) > 0) and dark.shape == (len(centres), 3)


def test_clear_air_has_no_backscatter_whatever_the_background():
    """No medium: the darkest surfaces stay dark at every range, so the backscatter is nil even under
    a bright veil (a bright sky is not veiling light)."""
    z, image = observations(np.zeros(3), np.zeros(3), np.zeros(3))
    centres, dark = dark_envelope(z, image)
    for veil in (None, np.array([0.8, 0.85, 0.9])):
        fit = fit_envelope(centres, dark, veil)
        assert fit.backscatter(centres.max()).max() < 1e-3


def test_the_envelope_scales_with_the_unit():
    """Ranges in centimetres give densities per centimetre: the same backscatter at the same place."""
    z, image = observations(VEIL, BETA_B, BETA_D)
    metres = fit_envelope(*dark_envelope(z, image), VEIL)
    centimetres = fit_envelope(*dark_envelope(100 * z, image), VEIL)
    np.testing.assert_allclose(centimetres.beta_B * 100, metres.beta_B, rtol=1e-3)


def test_bad_observations_are_left_out_or_refused():
    z, image = observations(VEIL, BETA_B, BETA_D, n=600)
    z[:50], image[50:100] = np.nan, np.inf
    centres, dark = dark_envelope(z, image)
    assert np.isfinite(centres).all() and np.isfinite(dark).all()
    with pytest.raises(ValueError, match="usable observations"):
        dark_envelope(np.full(10, np.nan), np.zeros((10, 3)))
    with pytest.raises(ValueError, match="quantile"):
        dark_envelope(z, image, quantile=1.0)
