"""The depth loss's kernel follows the sampling: closed forms, and the gradient it restores."""

import torch
from nerfstudio.model_components.losses import ds_nerf_depth_loss

from seathru_nerfstudio.losses import depth_kernel_variance


def _intervals(edges):
    """Starts and ends [1, S, 1] from S + 1 edges along one ray."""
    edges = torch.as_tensor(edges, dtype=torch.float32)
    return edges[:-1].view(1, -1, 1), edges[1:].view(1, -1, 1)


def test_coarse_samples_widen_the_kernel_to_their_spacing():
    starts, ends = _intervals(torch.arange(0.0, 10.01, 0.5))
    variance = depth_kernel_variance(starts, ends, torch.tensor([[4.1]]), sigma_floor=0.02)
    assert variance.shape == (1, 1, 1)
    assert torch.allclose(variance, torch.tensor(0.25))


def test_dense_samples_keep_the_floor():
    starts, ends = _intervals(torch.arange(0.0, 1.001, 0.01))
    variance = depth_kernel_variance(starts, ends, torch.tensor([[0.5]]), sigma_floor=0.05)
    assert torch.allclose(variance, torch.tensor(0.05**2))


def test_the_interval_nearest_the_depth_sets_the_width():
    # Midpoints 0.05, 0.2, 0.5, 1.1, 2.3 with lengths 0.1, 0.2, 0.4, 0.8, 1.6; outside the
    # sampled range the end interval counts.
    starts, ends = _intervals([0.0, 0.1, 0.3, 0.7, 1.5, 3.1])
    ranges = torch.tensor([[2.0], [0.05], [1.0], [50.0]])
    variance = depth_kernel_variance(starts.expand(4, -1, -1), ends.expand(4, -1, -1), ranges, sigma_floor=0.0)
    assert torch.allclose(variance.flatten(), torch.tensor([1.6, 0.1, 0.8, 1.6]) ** 2)


def test_the_width_is_not_trained():
    starts, ends = _intervals(torch.arange(0.0, 5.01, 1.0))
    starts.requires_grad_(True)
    variance = depth_kernel_variance(starts, ends, torch.tensor([[2.2]]), sigma_floor=0.1)
    assert not variance.requires_grad


def test_a_narrow_fixed_kernel_between_samples_gives_no_gradient_and_the_widened_one_does():
    """Samples 0.5 apart, depth 4.2, nearest midpoint 4.25. A fixed 2 cm kernel weighs it by
    e^{-0.05^2 / (2 * 0.02^2)} ~ 0.04 and its neighbours by e^{-253} (0 in float32); widened to
    0.5, the nearest gets the largest pull and its neighbours more than a tenth of it."""
    starts, ends = _intervals(torch.arange(0.0, 10.01, 0.5))
    midpoints = 0.5 * (starts + ends)
    depth = torch.tensor([[4.2]])

    def pull(variance):
        weights = torch.full_like(starts, 1.0 / starts.shape[-2]).requires_grad_(True)
        ds_nerf_depth_loss(weights, depth, midpoints, ends - starts, variance).backward()
        return -weights.grad.flatten()  # > 0: the loss wants more weight there

    fixed = pull(torch.tensor(0.02**2))
    widened = pull(depth_kernel_variance(starts, ends, depth, sigma_floor=0.02))
    nearest = int(torch.argmin((midpoints.flatten() - 4.2).abs()))
    assert fixed[nearest - 1] < 1e-30 and fixed[nearest + 1] < 1e-30
    assert widened[nearest] == widened.max()
    assert widened[nearest - 1] > 0.1 * widened[nearest] and widened[nearest + 1] > 0.1 * widened[nearest]
    # Far samples still get (next to) nothing: the kernel is local.
    assert widened[0] < 1e-6 * widened[nearest]


def test_finite_for_extreme_ranges():
    starts, ends = _intervals([0.0, 1e-6, 1.0, 1e6])
    ranges = torch.tensor([[0.0], [1e30], [-5.0]])
    variance = depth_kernel_variance(starts.expand(3, -1, -1), ends.expand(3, -1, -1), ranges, sigma_floor=1e-3)
    assert torch.isfinite(variance).all() and (variance > 0).all()


def test_the_variance_stays_finite_for_huge_intervals():
    """A spacing of 1e30 squared would overflow float32 (and 1e200 float64); the width is capped instead."""
    for dtype, huge in ((torch.float32, 1e30), (torch.float64, 1e200)):
        starts = torch.tensor([0.0, huge], dtype=dtype).view(1, 2, 1)
        ends = torch.tensor([huge, 2 * huge], dtype=dtype).view(1, 2, 1)
        variance = depth_kernel_variance(starts, ends, torch.tensor([[0.1 * huge]], dtype=dtype), sigma_floor=0.01)
        assert torch.isfinite(variance).all()
        assert variance.item() >= 0.99 * torch.finfo(dtype).max  # capped at the top, not shrunk


def test_clear_air_weighs_the_sfm_depths_by_its_own_weight():
    """Under ``none`` the depth loss takes ``clear_air_depth_loss_mult``, with a medium
    ``depth_loss_mult``: the same rays and weights give the same DS-NeRF loss, scaled by each."""
    from nerfstudio.cameras.rays import RayBundle
    from tiny_training import tiny_model

    from seathru_nerfstudio.medium_field import MEDIUM_MODELS

    generator = torch.Generator().manual_seed(3)
    bundle = RayBundle(
        origins=torch.randn(16, 3, generator=generator) * 0.1,
        directions=torch.nn.functional.normalize(torch.randn(16, 3, generator=generator), dim=-1),
        pixel_area=torch.full((16, 1), 1e-4),
        camera_indices=torch.zeros(16, 1, dtype=torch.long),
        metadata={"directions_norm": torch.ones(16, 1)},
    )
    depth = torch.full((16, 1), 0.6)
    depth[8:] = 0.0  # unknown
    batch = {"image": torch.rand(16, 3, generator=generator), "depth_image": depth}
    model = tiny_model(medium_model="seathru", medium_first_steps=0, depth_loss_mult=0.1, clear_air_depth_loss_mult=0.01)
    model.train()
    losses = {}
    for name in ("seathru", "none"):
        model.medium_model_code.fill_(MEDIUM_MODELS.index(name))
        torch.manual_seed(0)  # the proposal samplers' jitter
        out = model(bundle)
        losses[name] = model.get_loss_dict(out, batch, model.get_metrics_dict(out, batch))["depth_loss"]
    assert model.clear_air and losses["none"] > 0
    torch.testing.assert_close(losses["none"] / losses["seathru"], torch.tensor(0.1))
    model.config.clear_air_depth_loss_mult = 0.0
    out = model(bundle)
    assert "depth_loss" not in model.get_loss_dict(out, batch, model.get_metrics_dict(out, batch))
