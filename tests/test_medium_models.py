"""Medium models from ``none`` to ``seathru``: what each renders and trains, and how the tied ones
reduce to ``seathru`` (``auto``'s choice between them: test_auto_decision.py)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from nerfstudio.data.scene_box import SceneBox
from nerfstudio.models.nerfacto import NerfactoModelConfig

from seathru_nerfstudio import metrics
from seathru_nerfstudio.medium_field import MediumOutputs, tie
from seathru_nerfstudio.losses import rawnerf_loss
from seathru_nerfstudio.rendering import render_seathru

from tiny_training import rays, spy_calls, tiny_model


def count_medium_calls(model) -> list:
    """The calls of the model's medium, from now on."""
    return spy_calls(model.medium_field)


def test_none_renders_what_nerfacto_renders_from_the_same_field_and_never_calls_the_medium():
    torch.manual_seed(0)
    ours = tiny_model(medium_model="none", object_view_dependent=True)
    kwargs = {
        f.name: getattr(ours.config, f.name)
        for f in dataclasses.fields(NerfactoModelConfig)
        if f.init and f.name not in ("_target", "background_color")  # nerfacto's own background
    }
    with metrics.offline_lpips():
        nerfacto = NerfactoModelConfig(**kwargs).setup(
            scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]])), num_train_data=4
        )
    ours_state = ours.state_dict()
    missing = [key for key in nerfacto.state_dict() if key not in ours_state]
    assert not missing, missing
    nerfacto.load_state_dict({key: ours_state[key] for key in nerfacto.state_dict()})
    calls = count_medium_calls(ours)
    bundle = rays(64, seed=3)
    for training in (True, False):
        ours.train(training)
        nerfacto.train(training)
        torch.manual_seed(1)  # the proposal sampler jitters while training
        mine = ours(bundle)
        torch.manual_seed(1)
        theirs = nerfacto(bundle)
        for name in ("rgb", "accumulation", "depth", "expected_depth"):
            torch.testing.assert_close(mine[name], theirs[name], rtol=0, atol=1e-6, msg=name)
        torch.testing.assert_close(mine["clean"], mine["rgb"], rtol=0, atol=0)
        torch.testing.assert_close(mine["direct"], mine["rgb"], rtol=0, atol=0)
        for name in ("backscatter", "medium_rgb", "medium_attenuation", "medium_backscatter"):
            assert mine[name].shape == (64, 3) and bool((mine[name] == 0).all()), name
    assert calls == []
    assert ours.object_frozen is False or ours.train_step is None


def test_none_trains_from_step_0_with_no_medium_stage():
    model = tiny_model(medium_model="none")
    model.train()
    model.train_step = 0
    assert not model.object_frozen
    out = model(rays(16))
    losses = model.get_loss_dict(out, {"image": torch.rand(16, 3)}, model.get_metrics_dict(out, {"image": torch.rand(16, 3)}))
    sum(losses.values()).backward()
    assert all(p.grad is None for p in model.medium_field.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.field.parameters())


def losses_of(model, seed: int = 0) -> dict:
    model.train()
    out = model(rays(16, seed=seed))
    target = torch.rand(16, 3, generator=torch.Generator().manual_seed(seed))
    batch = {"image": target}
    return model.get_loss_dict(out, batch, model.get_metrics_dict(out, batch)), out, target


def test_clear_air_trains_with_nerfactos_objective():
    """``none`` on linear data: nerfacto's L2 and no prior (clear air has no medium for the relative
    loss and the prior to tell apart); a medium model keeps the relative loss and the prior."""
    none = tiny_model(medium_model="none")
    losses, out, target = losses_of(none)
    torch.testing.assert_close(losses["rgb_loss"], torch.mean((out["rgb"] - target) ** 2))
    assert "binary_prior_loss" not in losses
    seathru = tiny_model(medium_model="seathru")
    losses, out, target = losses_of(seathru)
    torch.testing.assert_close(losses["rgb_loss"], rawnerf_loss(out["rgb"], target))
    assert "binary_prior_loss" in losses


def test_tie_averages_the_densities_as_each_model_asks():
    gen = torch.Generator().manual_seed(0)
    medium = MediumOutputs(
        rgb=torch.rand(5, 3, generator=gen), sigma_attn=torch.rand(5, 3, generator=gen), sigma_bs=torch.rand(5, 3, generator=gen)
    )
    fog = tie(medium, "fog")  # grey attenuation: averaged over the channels; the backscatter density kept
    torch.testing.assert_close(fog.sigma_attn, medium.sigma_attn.mean(dim=-1, keepdim=True).expand(5, 3))
    assert torch.equal(fog.sigma_bs, medium.sigma_bs)
    for name in ("uniform", "basic"):
        tied = tie(medium, name)
        torch.testing.assert_close(tied.sigma_attn, (medium.sigma_attn + medium.sigma_bs) / 2)
        torch.testing.assert_close(tied.sigma_bs, tied.sigma_attn)
    assert tie(medium, "seathru") is medium
    with pytest.raises(ValueError, match="none"):
        tie(medium, "none")
    # an overflowed density stays in its own group: no 0*inf leaks NaN into the other channels
    attn = medium.sigma_attn.clone().bfloat16()
    attn[:, 0] = float("inf")
    overflowed = tie(MediumOutputs(rgb=medium.rgb, sigma_attn=attn, sigma_bs=medium.sigma_bs.bfloat16()), "uniform")
    assert overflowed.sigma_attn.dtype == torch.bfloat16
    assert torch.isinf(overflowed.sigma_attn[:, 0]).all() and torch.isfinite(overflowed.sigma_attn[:, 1:]).all()


@pytest.mark.parametrize("name", ["fog", "uniform"])
def test_fog_and_uniform_reduce_exactly_to_seathru_with_tied_parameters(name):
    torch.manual_seed(0)
    tied = tiny_model(medium_model=name, medium_scope="scene")
    full = tiny_model(medium_model="seathru", medium_scope="scene")
    state = tied.state_dict()
    with torch.no_grad():
        raw = tied.medium_field.density_raw
        if name == "fog":
            raw[:3], raw[3:] = 0.3, torch.tensor([-0.2, 0.4, -0.9])
        else:
            raw[3:] = raw[:3] = torch.tensor([0.1, -0.4, 0.7])
        state = {key: value for key, value in tied.state_dict().items() if key != "medium_model_code"}
    full.load_state_dict(state, strict=False)
    tied.eval()
    full.eval()
    bundle = rays(32, seed=4)
    a, b = tied(bundle), full(bundle)
    for key in ("rgb", "clean", "direct", "backscatter", "medium_attenuation", "medium_backscatter", "depth"):
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=key)


def test_uniform_medium_renders_as_seathru_with_equal_densities():
    """The formula behind ``uniform``: the renderer with sigma_attn = sigma_bs (closed form of an
    opaque wall at range z: J e^{-beta z} + B (1 - e^{-beta z}))."""
    beta = torch.tensor([[0.4, 0.7, 1.1]])
    z = 2.5
    starts = torch.tensor([[[0.0], [z]]])
    deltas = torch.tensor([[[z], [1.0]]])
    density = torch.tensor([[[0.0], [1e6]]])
    colour = torch.tensor([[[0.0, 0.0, 0.0], [0.8, 0.5, 0.3]]])
    veil = torch.tensor([[0.1, 0.3, 0.5]])
    out = render_seathru(colour, density, starts, deltas, veil, beta, beta)
    expected = colour[:, 1] * torch.exp(-beta * z) + veil * -torch.expm1(-beta * z)
    torch.testing.assert_close(out.rgb, expected, rtol=1e-5, atol=1e-6)
