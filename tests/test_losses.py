"""The backscatter envelope loss: its minimiser, its limits, and finiteness on extreme input."""

import math

import pytest
import torch

from seathru_nerfstudio.losses import backscatter_envelope_loss


def _scene(num: int, sigma: float, veil, dark_fraction: float, seed: int = 0):
    """Pixels I = J e^{-beta_D r} + veil (1 - e^{-sigma r}), a fraction of them black (J = 0)."""
    g = torch.Generator().manual_seed(seed)
    r = 0.5 + 4.0 * torch.rand(num, 1, generator=g)
    J = torch.rand(num, 3, generator=g)
    J[torch.rand(num, generator=g) < dark_fraction] = 0.0
    veil = torch.tensor(veil).expand(num, 3)
    image = J * torch.exp(-1.3 * sigma * r) + veil * -torch.expm1(-sigma * r)
    return image, r, veil


@pytest.mark.parametrize("true_sigma", [0.2, 1.0, 3.0])
def test_fitting_the_envelope_recovers_the_backscatter_density(true_sigma):
    """Per channel, the loss's minimiser over densities from 0.01 to 10 (steps of 0.6%) is within
    5% of the truth, and its gradient points towards the truth from 30% above and below it."""
    image, r, veil = _scene(4000, true_sigma, [0.07, 0.2, 0.39], dark_fraction=0.05)
    grid = torch.logspace(-2, 1, 1201)
    for c in range(3):
        channel = image[:, c : c + 1], r, veil[:, c : c + 1]
        losses = torch.stack([backscatter_envelope_loss(*channel, torch.full((4000, 1), float(s)), 0.01) for s in grid])
        torch.testing.assert_close(grid[losses.argmin()], torch.tensor(true_sigma), rtol=0.05, atol=0)
        for factor, sign in ((1.3, 1.0), (1 / 1.3, -1.0)):
            sigma = torch.full((4000, 1), true_sigma * factor, requires_grad=True)
            backscatter_envelope_loss(*channel, sigma, 0.01).backward()
            assert sign * float(sigma.grad.sum()) > 0, (c, factor)


def test_the_minimiser_leaves_the_quantile_below():
    # One channel, backscatter is a constant b here (sigma r -> inf): the pinball loss is
    # minimised where a fraction q of the pixels lies below b.
    image = torch.linspace(0.0, 1.0, 1001)[:, None].expand(1001, 3)
    r = torch.full((1001, 1), 1e6)
    sigma = torch.ones(1001, 3)
    losses = []
    candidates = torch.linspace(0.0, 0.2, 201)
    for b in candidates:
        losses.append(float(backscatter_envelope_loss(image, r, torch.full((1001, 3), float(b)), sigma, 0.05)))
    best = float(candidates[int(torch.tensor(losses).argmin())])
    assert abs(best - 0.05) <= 0.002


def test_rays_without_a_range_are_left_out():
    image, r, veil = _scene(100, 1.0, [0.1, 0.2, 0.3], 0.1)
    sigma = torch.full((100, 3), 0.7)
    reference = backscatter_envelope_loss(image[:50], r[:50], veil[:50], sigma[:50])
    r_unknown = r.clone()
    r_unknown[50:] = 0.0
    r_unknown[75:] = math.inf
    torch.testing.assert_close(backscatter_envelope_loss(image, r_unknown, veil, sigma), reference)
    no_range = torch.zeros_like(r)
    assert float(backscatter_envelope_loss(image, no_range, veil, sigma)) == 0.0


def test_finite_with_gradients_for_extreme_densities_and_ranges():
    image = torch.rand(6, 3)
    r = torch.tensor([[1e-9], [1e-3], [1.0], [1e3], [1e6], [1e30]])
    for value in (0.0, 1e-12, 1.0, 1e6, 1e18):
        sigma = torch.full((6, 3), value, requires_grad=True)
        loss = backscatter_envelope_loss(image, r, torch.full((6, 3), 0.5), sigma)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(sigma.grad).all()


def test_quantile_out_of_range_is_refused():
    with pytest.raises(ValueError, match="quantile"):
        backscatter_envelope_loss(torch.zeros(1, 3), torch.ones(1, 1), torch.zeros(1, 3), torch.ones(1, 3), 1.0)


def test_backscatter_excess_is_zero_below_the_image_and_relative_above():
    from seathru_nerfstudio.losses import backscatter_excess_loss

    image = torch.tensor([[0.2, 0.1, 0.4], [0.05, 0.3, 0.0]])
    below = image * 0.9
    assert backscatter_excess_loss(below, image) == 0
    backscatter = torch.tensor([[0.3, 0.05, 0.4], [0.05, 0.6, 0.01]], requires_grad=True)
    loss = backscatter_excess_loss(backscatter, image, eps=1e-3)
    excess = torch.tensor([[0.1 / 0.201, 0.0, 0.0], [0.0, 0.3 / 0.301, 0.01 / 0.001]])
    torch.testing.assert_close(loss, (excess**2).mean())
    loss.backward()
    # only the pixels whose backscatter is above the image get a gradient, and it lowers them
    assert (backscatter.grad[excess == 0] == 0).all() and (backscatter.grad[excess > 0] > 0).all()
    # finite difference of one entry above the image
    h = 1e-4
    bumped = backscatter.detach().clone()
    bumped[1, 1] += h
    numeric = (backscatter_excess_loss(bumped, image) - backscatter_excess_loss(backscatter.detach(), image)) / h
    torch.testing.assert_close(backscatter.grad[1, 1], numeric, rtol=1e-2, atol=0)


def test_backscatter_excess_is_finite_for_extreme_input():
    from seathru_nerfstudio.losses import backscatter_excess_loss

    backscatter = torch.tensor([[3e38, 0.0, 1e-30]], requires_grad=True)
    image = torch.tensor([[0.0, 1e30, -1.0]])
    loss = backscatter_excess_loss(backscatter, image)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(backscatter.grad).all()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        small = backscatter_excess_loss(torch.tensor([[0.5, 0.1, 0.2]]), torch.tensor([[0.1, 0.1, 0.0]]))
    assert torch.isfinite(small)
