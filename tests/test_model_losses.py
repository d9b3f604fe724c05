"""SeathruModel's losses: the paper's terms and their gradients, the backscatter excess, the
binary prior, and the depth loss on the SfM depths."""

from __future__ import annotations

import pytest
import torch

from seathru_nerfstudio.losses import binary_transmittance_loss, rawnerf_loss
from seathru_nerfstudio.model import SeathruModel

from tiny_training import rays, seeded_tiny_model, tiny_model


@pytest.fixture(scope="module")
def model() -> SeathruModel:
    return seeded_tiny_model()


def test_loss_dict_has_the_paper_terms_and_finite_gradients(model):
    model.train()
    bundle = rays(48, seed=2)
    out = model(bundle)
    target = torch.rand(48, 3)
    batch = {"image": target}
    metrics_dict = model.get_metrics_dict(out, batch)
    losses = model.get_loss_dict(out, batch, metrics_dict)
    assert set(losses) >= {"rgb_loss", "interlevel_loss", "binary_prior_loss"}
    torch.testing.assert_close(losses["rgb_loss"], rawnerf_loss(out["rgb"], target))
    weight = model.config.binary_prior_mult  # a loaded model: no training step, the weight after the schedule
    torch.testing.assert_close(
        losses["binary_prior_loss"], weight * binary_transmittance_loss(out["transmittance"], scale=0.1, empty_weight=6.0)
    )
    total = sum(losses.values())
    total.backward()
    medium_grads = [p.grad for p in model.medium_field.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in medium_grads)
    assert any(g.abs().sum() > 0 for g in medium_grads)
    groups = model.get_param_groups()
    medium_params = set(groups.get("medium", [])) | set(groups.get("medium_density", []))
    assert all(p in medium_params for p in model.medium_field.parameters())
    model.zero_grad()


def test_backscatter_excess_moves_the_backscatter_density_only():
    from seathru_nerfstudio.losses import backscatter_excess_loss

    m = tiny_model(backscatter_excess_mult=2.0, medium_scope="scene", medium_model="seathru", medium_first_steps=0)
    m.train()
    out = m(rays(32, seed=3))
    target = torch.zeros(32, 3)  # a black image: every bit of backscatter is excess
    losses = m.get_loss_dict(out, {"image": target}, m.get_metrics_dict(out, {"image": target}))
    # the held-geometry backscatter is the one rendered (same geometry, same medium)
    torch.testing.assert_close(out["backscatter_geometry_held"], out["backscatter"])
    torch.testing.assert_close(losses["backscatter_excess_loss"], 2.0 * backscatter_excess_loss(out["backscatter"], target))
    m.zero_grad()
    losses["backscatter_excess_loss"].backward()
    assert m.medium_field.density_raw.grad is not None and m.medium_field.density_raw.grad[3:].abs().sum() > 0
    assert m.medium_field.rgb_logit.grad is None or m.medium_field.rgb_logit.grad.abs().sum() == 0  # veil held
    field_grads = [p.grad for p in m.field.parameters() if p.grad is not None and p.grad.abs().sum() > 0]
    assert not field_grads  # the surfaces are not moved to lower the backscatter
    m.eval()
    with torch.no_grad():
        assert "backscatter_geometry_held" not in m(rays(4))
    off = tiny_model(backscatter_excess_mult=0.0, medium_first_steps=0)
    off.train()
    out = off(rays(8, seed=5))
    batch = {"image": torch.rand(8, 3)}
    assert "backscatter_excess_loss" not in off.get_loss_dict(out, batch, off.get_metrics_dict(out, batch))
    early = tiny_model(backscatter_excess_mult=2.0, backscatter_excess_steps=10, medium_first_steps=0)
    early.train()
    for step, expected in ((9, True), (10, False)):
        early.train_step = step
        out = early(rays(8, seed=5))
        batch = {"image": torch.rand(8, 3)}
        losses = early.get_loss_dict(out, batch, early.get_metrics_dict(out, batch))
        assert ("backscatter_excess_loss" in losses) == expected, step


def test_srgb_data_trains_with_plain_l2():
    model = tiny_model(color_space="srgb")
    model.train()
    out = model(rays(16))
    target = torch.rand(16, 3)
    losses = model.get_loss_dict(out, {"image": target}, model.get_metrics_dict(out, {"image": target}))
    torch.testing.assert_close(losses["rgb_loss"], torch.mean((out["rgb"] - target) ** 2))


def test_asymmetric_binary_prior_prefers_empty_space():
    t = torch.tensor([[0.0], [1.0]])
    symmetric = [binary_transmittance_loss(t[i : i + 1]) for i in range(2)]
    torch.testing.assert_close(symmetric[0], symmetric[1])
    opaque, empty = (binary_transmittance_loss(t[i : i + 1], empty_weight=6.0) for i in range(2))
    # -log(1 + 6 e^-10) at T=0 against -log(6 + e^-10) at T=1
    torch.testing.assert_close(opaque, -torch.log(1 + 6 * torch.exp(torch.tensor(-10.0))))
    torch.testing.assert_close(empty, -torch.log(6 + torch.exp(torch.tensor(-10.0))))
    with pytest.raises(ValueError):
        binary_transmittance_loss(t, empty_weight=0.0)


def test_depth_loss_pulls_the_weights_to_the_known_depth_and_empties_open_water(model):
    """Sparse (z-depth, 0 = unknown) and oracle (range, inf = open water) depth supervision."""
    for source in ("sfm", "ground-truth"):
        m = tiny_model(depth_loss_mult=1.0, depth_source=source, depth_sigma=0.05)
        m.train()
        bundle = rays(32, seed=4)
        bundle.metadata["directions_norm"] = torch.ones(32, 1)
        out = m(bundle)
        depth = torch.full((32, 1), 0.6)
        if source == "sfm":
            depth[16:] = 0.0  # unknown
            batch = {"image": torch.rand(32, 3), "depth_image": depth}
        else:
            depth[16:] = float("inf")  # open water
            batch = {"image": torch.rand(32, 3), "gt_depth": depth}
        loss = m.get_loss_dict(out, batch, m.get_metrics_dict(out, batch))["depth_loss"]
        assert torch.isfinite(loss) and loss > 0
        loss.backward()
        grads = [p.grad for p in m.field.parameters() if p.grad is not None]
        assert grads and all(torch.isfinite(g).all() for g in grads)
    m = tiny_model(depth_loss_mult=1.0)  # a dataset without depth images trains without the term
    m.train()
    out = m(rays(4))
    batch = {"image": torch.rand(4, 3)}
    assert "depth_loss" not in m.get_loss_dict(out, batch, m.get_metrics_dict(out, batch))
    with pytest.raises(KeyError, match="depth_source ground-truth"):
        m = tiny_model(depth_loss_mult=1.0, depth_source="ground-truth")
        m.train()
        out = m(rays(4))
        m.get_loss_dict(out, batch, m.get_metrics_dict(out, batch))


def test_the_depth_loss_kernel_follows_the_samples():
    """The model's depth loss is nerfstudio's DS-NeRF loss with, per ray, the variance of
    :func:`depth_kernel_variance` (the floor, or the sample interval at the known range), averaged
    over the rays whose depth is known."""
    from nerfstudio.model_components.losses import DepthLossType, depth_loss

    from seathru_nerfstudio.losses import depth_kernel_variance

    bundle = rays(8, seed=5)
    norm = torch.full((8, 1), 1.25)
    bundle.metadata["directions_norm"] = norm
    z_depth = torch.full((8, 1), 0.6)
    z_depth[6:] = 0.0  # unknown
    m = tiny_model(depth_loss_mult=1.0, depth_sigma=0.05)
    m.train()
    out = m(bundle)
    frustums = out["ray_samples_list"][-1].frustums
    variance = depth_kernel_variance(frustums.starts, frustums.ends, z_depth * norm, 0.05 * m.world_scale)
    assert variance.shape == (8, 1, 1) and (variance >= (0.05 * m.world_scale) ** 2).all()
    expected = depth_loss(
        weights=out["weights_list"][-1], ray_samples=out["ray_samples_list"][-1], termination_depth=z_depth,
        predicted_depth=out["expected_depth"], sigma=variance, directions_norm=norm, is_euclidean=False,
        depth_loss_type=DepthLossType.DS_NERF,
    ) * 8 / 6  # fmt: skip
    torch.testing.assert_close(m._depth_loss(out, {"depth_image": z_depth}), expected)
