"""SeathruModel glue: outputs contract, per-ray medium, losses, offline LPIPS, checkpoints."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.field_components.field_heads import FieldHeadNames

from seathru_nerfstudio import metrics
from seathru_nerfstudio.losses import binary_transmittance_loss, rawnerf_loss
from seathru_nerfstudio.medium_fit import apply_medium_fit
from seathru_nerfstudio.model import SeathruModel, SeathruModelConfig

from tiny_training import spy_calls, tiny_model

CONTRACT = (
    "rgb",
    "clean",
    "direct",
    "backscatter",
    "depth",
    "accumulation",
    "medium_rgb",
    "medium_attenuation",
    "medium_backscatter",
    "prop_depth_0",
    "prop_depth_1",
)


def rays(num: int, seed: int = 0) -> RayBundle:
    gen = torch.Generator().manual_seed(seed)
    directions = torch.nn.functional.normalize(torch.randn(num, 3, generator=gen), dim=-1)
    return RayBundle(
        origins=torch.randn(num, 3, generator=gen) * 0.1,
        directions=directions,
        pixel_area=torch.full((num, 1), 1e-4),
        camera_indices=torch.zeros(num, 1, dtype=torch.long),
    )


@pytest.fixture(scope="module")
def model() -> SeathruModel:
    torch.manual_seed(0)
    return tiny_model()


def test_outputs_follow_the_contract_and_are_finite(model):
    model.eval()
    with torch.no_grad():
        out = model(rays(64))
    for name in CONTRACT:
        assert name in out, name
        assert out[name].shape[0] == 64
        assert torch.isfinite(out[name]).all(), name
    for name in ("rgb", "clean", "direct", "backscatter", "medium_rgb", "medium_attenuation"):
        assert out[name].shape == (64, 3), name
    torch.testing.assert_close(out["rgb"], out["direct"] + out["backscatter"])
    assert (out["medium_attenuation"] > 0).all() and (out["medium_backscatter"] > 0).all()
    assert ((out["medium_rgb"] > 0) & (out["medium_rgb"] < 1)).all()


def test_medium_is_evaluated_once_per_ray(model):
    model.train()
    calls = spy_calls(model.medium_field)
    try:
        model(rays(32))
    finally:
        del model.medium_field.forward
    assert calls == [torch.Size([32, 3])]


def test_medium_is_constant_along_a_ray_and_depends_on_direction_only(model):
    model.eval()
    bundle = rays(16, seed=1)
    shifted = rays(16, seed=1)
    shifted.origins = shifted.origins + torch.tensor([0.3, -0.2, 0.1])
    with torch.no_grad():
        a, b = model(bundle), model(shifted)
    for name in ("medium_rgb", "medium_attenuation", "medium_backscatter"):
        torch.testing.assert_close(a[name], b[name])


def test_basic_model_ties_attenuation_to_backscatter():
    model = tiny_model(medium_model="basic")
    model.eval()
    with torch.no_grad():
        out = model(rays(16))
    torch.testing.assert_close(out["medium_attenuation"], out["medium_backscatter"])


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


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_model_outputs_stay_finite_under_autocast(model, dtype):
    model.train()
    with torch.autocast(device_type="cpu", dtype=dtype):
        out = model(rays(32, seed=3))
        loss = rawnerf_loss(out["rgb"], torch.rand(32, 3))
    for name in CONTRACT:
        if name.startswith("prop_depth"):  # training computes only what the losses read
            assert name not in out, name
            continue
        assert torch.isfinite(out[name].float()).all(), name
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    model.zero_grad()


def test_lpips_is_skipped_offline_with_one_warning(tmp_path, monkeypatch):
    monkeypatch.setattr(metrics, "_warned", False)
    old = torch.hub.get_dir()
    torch.hub.set_dir(str(tmp_path / "empty_hub"))
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            first = tiny_model()
            second = tiny_model()
    finally:
        torch.hub.set_dir(old)
    assert first.lpips is None and second.lpips is None
    lpips_warnings = [w for w in caught if "LPIPS disabled" in str(w.message)]
    assert len(lpips_warnings) == 1
    outputs = {k: torch.rand(6, 8, 3) for k in ("rgb", "clean", "backscatter")}
    outputs.update(depth=torch.rand(6, 8, 1), accumulation=torch.rand(6, 8, 1))
    scores, _ = first.get_image_metrics_and_images(outputs, {"image": torch.rand(6, 8, 3)})
    assert "lpips" not in scores and "psnr" in scores


def test_lpips_is_used_when_its_weights_are_on_disk(tmp_path):
    import torchvision

    hub = tmp_path / "hub"
    (hub / "checkpoints").mkdir(parents=True)
    torch.save(torchvision.models.alexnet(weights=None).state_dict(), hub / "checkpoints" / metrics.ALEXNET_WEIGHTS)
    old = torch.hub.get_dir()
    torch.hub.set_dir(str(hub))
    try:
        model = tiny_model()
    finally:
        torch.hub.set_dir(old)
    assert model.lpips is not None
    outputs = {k: torch.rand(32, 32, 3) for k in ("rgb", "clean", "backscatter")}
    outputs.update(depth=torch.rand(32, 32, 1), accumulation=torch.rand(32, 32, 1))
    scores, _ = model.get_image_metrics_and_images(outputs, {"image": torch.rand(32, 32, 3)})
    assert "lpips" in scores and scores["lpips"] == scores["lpips"]


def test_eval_metrics_against_ground_truth():
    model = tiny_model()
    height, width = 8, 10
    clean = torch.rand(height, width, 3)
    depth = torch.full((height, width, 1), 2.0)
    depth[:2] = float("inf")  # open water rows
    outputs = {
        "rgb": clean.clone(),
        "clean": clean.clone(),
        "backscatter": torch.zeros(height, width, 3),
        "depth": depth.clone().nan_to_num(posinf=50.0) * 1.5,
        "accumulation": torch.ones(height, width, 1),
    }
    outputs["clean"][:2] = 0.7  # open water: ignored by clean metrics
    batch = {"image": clean.clone(), "gt_clean": clean.clone(), "gt_depth": depth}
    scores, images = model.get_image_metrics_and_images(outputs, batch)
    assert scores["clean_psnr"] > 100
    assert scores["depth_abs_rel"] == pytest.approx(0.5)
    assert scores["depth_abs_rel_far"] == pytest.approx(0.5)
    assert {"img", "clean", "backscatter", "depth"} <= set(images)


def test_nerfstudio_checkpoints_load_with_weights_only(tmp_path):
    """torch >= 2.6 refuses nerfstudio checkpoints (NumPy scalars) unless our package is imported."""
    import numpy as np

    path = tmp_path / "step-000000001.ckpt"
    torch.save({"step": 1, "schedulers": {"fields": {"_last_lr": [np.float64(0.01)], "base": np.int64(3)}}}, path)
    load = f"import torch; torch.load({str(path)!r}, map_location='cpu')"
    plain = subprocess.run([sys.executable, "-c", load], capture_output=True, text=True)  # a fresh process
    assert plain.returncode != 0 and "weights_only" in plain.stderr.lower() + plain.stdout.lower()
    import seathru_nerfstudio.config  # noqa: F401  (what ns-train, ns-eval, ns-render import)

    assert torch.load(path, map_location="cpu")["schedulers"]["fields"]["base"] == 3


def test_collider_uses_the_scenes_near_bound_when_the_dataparser_gives_one():
    config = tiny_model().config
    box = SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    with_bounds = config.setup(scene_box=box, num_train_data=4, metadata={"near_plane": 0.5, "far_plane": 9.0})
    assert with_bounds.collider.near_plane == pytest.approx(0.45)
    assert tiny_model().collider.near_plane == config.near_plane


@pytest.mark.parametrize("render_from_near_bound, render_near", [(True, 0.45), (False, 0.0)])
def test_renders_start_at_the_near_bound_that_training_used(render_from_near_bound, render_near):
    """Outside training nerfstudio's collider starts rays at 0, in space no training ray sampled."""
    config = tiny_model(render_from_near_bound=render_from_near_bound).config
    box = SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    model = config.setup(scene_box=box, num_train_data=4, metadata={"near_plane": 0.5, "far_plane": 9.0})
    model.train()
    assert torch.allclose(model.collider(rays(4, seed=1)).nears, torch.full((4, 1), 0.45))
    model.eval()
    rendered = model.collider(rays(4, seed=1))
    assert torch.allclose(rendered.nears, torch.full((4, 1), render_near))
    assert torch.allclose(rendered.fars, torch.full((4, 1), 18.0))
    without_bounds = tiny_model(render_from_near_bound=render_from_near_bound)
    without_bounds.eval()
    expected = config.near_plane if render_from_near_bound else 0.0
    assert torch.allclose(without_bounds.collider(rays(4, seed=1)).nears, torch.full((4, 1), expected))


def test_the_step_callback_sets_the_training_step():
    model = tiny_model()
    callbacks = model.get_training_callbacks(None)
    callbacks[-1].run_callback_at_location(7, callbacks[-1].where_to_run[0])
    assert model.train_step == 7


def test_scene_medium_is_the_same_for_every_ray_and_learns():
    model = tiny_model(medium_scope="scene", medium_init_density=0.3)
    model.train()
    out = model(rays(16, seed=3))
    for name in ("medium_rgb", "medium_attenuation", "medium_backscatter"):
        torch.testing.assert_close(out[name], out[name][:1].expand(16, 3))
    torch.testing.assert_close(out["medium_attenuation"][0], torch.full((3,), 0.3))
    torch.testing.assert_close(out["medium_rgb"][0], torch.full((3,), 0.5))
    out["rgb"].sum().backward()
    groups = model.get_param_groups()
    # the veiling light learns fast, the densities slowly: two optimiser groups
    assert [p.shape for p in groups["medium"]] == [(3,)] and [p.shape for p in groups["medium_density"]] == [(6,)]
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in groups["medium"] + groups["medium_density"])


def test_the_model_learns_the_veil_from_open_rays(monkeypatch):
    """The model asks the renderer for ``veil_from_open_rays``: each ray's gradient on the veiling
    light is the plain one (the renderer without the flag) times 1 - accumulation."""
    import seathru_nerfstudio.model as model_module

    grads = []
    for plain in (True, False):
        if plain:
            render = model_module.render_seathru
            monkeypatch.setattr(model_module, "render_seathru", lambda **kw: render(**{**kw, "veil_from_open_rays": False}))
        torch.manual_seed(0)
        model = tiny_model(medium_scope="scene", medium_first_steps=0, average_init_density=3.0)
        model.train()
        out = model(rays(32, seed=5))
        (grad,) = torch.autograd.grad(out["rgb"].sum(), out["medium_rgb"])
        grads.append(grad)
        open_share = 1.0 - out["accumulation"].detach()
        monkeypatch.undo()
    assert ((open_share > 0.05) & (open_share < 0.95)).any()  # rays that are partly open
    torch.testing.assert_close(grads[1], grads[0] * open_share, rtol=1e-4, atol=1e-7)


def test_oracle_medium_is_the_truth_per_scene_unit_and_has_no_parameters(tmp_path):
    truth = {"beta_D": [1.3, 1.2, 0.9], "beta_B": [0.95, 0.85, 0.7], "B_inf": [0.07, 0.2, 0.39]}
    (tmp_path / "medium.json").write_text(__import__("json").dumps(truth))
    box = SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    config = tiny_model().config
    config.research.medium_oracle = tmp_path / "medium.json"
    model = config.setup(scene_box=box, num_train_data=4, metadata={"dataparser_scale": 2.5})
    model.eval()
    with torch.no_grad():
        out = model(rays(4))
    # 1/m divided by 2.5 scene units per metre
    torch.testing.assert_close(out["medium_attenuation"], torch.tensor([[1.3, 1.2, 0.9]]).expand(4, 3) / 2.5)
    torch.testing.assert_close(out["medium_backscatter"], torch.tensor([[0.95, 0.85, 0.7]]).expand(4, 3) / 2.5)
    torch.testing.assert_close(out["medium_rgb"], torch.tensor([[0.07, 0.2, 0.39]]).expand(4, 3))
    assert "medium" not in model.get_param_groups() and "medium_density" not in model.get_param_groups()
    assert config.medium_model == "seathru"  # the default auto has nothing to choose with an oracle


def test_lambertian_object_colour_does_not_depend_on_the_view_direction():
    torch.manual_seed(0)
    lambertian = tiny_model(object_view_dependent=False)
    torch.manual_seed(0)
    glossy = tiny_model(object_view_dependent=True)
    for model in (lambertian, glossy):
        model.eval()
    positions = torch.tensor([[0.1, 0.2, -0.3], [0.0, -0.1, 0.2]])
    colours = {}
    for name, model in (("lambertian", lambertian), ("glossy", glossy)):
        per_direction = []
        for direction in ([0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.8, 0.6]):
            d = torch.tensor(direction).expand(2, 3)
            bundle = RayBundle(
                origins=positions - 0.5 * d, directions=d, pixel_area=torch.full((2, 1), 1e-4),
                camera_indices=torch.zeros(2, 1, dtype=torch.long), nears=torch.full((2, 1), 0.5),
                fars=torch.full((2, 1), 0.5001),
            )
            samples = bundle.get_ray_samples(bin_starts=torch.full((2, 1, 1), 0.5), bin_ends=torch.full((2, 1, 1), 0.5001))
            with torch.no_grad():
                per_direction.append(model.field(samples)[FieldHeadNames.RGB])
        colours[name] = torch.stack(per_direction)
    torch.testing.assert_close(colours["lambertian"], colours["lambertian"][:1].expand_as(colours["lambertian"]))
    assert (colours["glossy"] - colours["glossy"][:1]).abs().max() > 1e-4  # the switch is what makes the difference


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


def test_the_medium_starts_at_an_optical_depth_of_the_sfm_range():
    """Densities per scene unit = optical depth / (mean SfM range in metres * scene units per metre)."""
    from seathru_nerfstudio.data.nerfstudio_data import RANGE_SPREAD_KEY, SCALE_KEY
    from seathru_nerfstudio.data.range_diversity import RangeSpread

    spread = RangeSpread(num_points=10, mean_views=3.0, mean_range=4.0, spread=0.1)
    directions = torch.nn.functional.normalize(torch.randn(5, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    for optical_depth in (3.0, 0.7):
        m = tiny_model(metadata={SCALE_KEY: 2.0, RANGE_SPREAD_KEY: spread}, medium_init_optical_depth=optical_depth)
        medium = m.medium_field(directions)
        for sigma in (medium.sigma_attn, medium.sigma_bs):  # per scene unit; the range is 4 m = 8 units
            torch.testing.assert_close(sigma * 8.0, torch.full_like(sigma, optical_depth))
        ray = tiny_model(metadata={SCALE_KEY: 2.0, RANGE_SPREAD_KEY: spread}, medium_init_optical_depth=optical_depth, medium_scope="ray")
        bias = torch.nn.functional.softplus(ray.medium_field.density_bias)
        torch.testing.assert_close(bias * 8.0, torch.full_like(bias, optical_depth))
    # Without SfM depths, switched off, or a degenerate range whose density would be inf: medium_init_density.
    degenerate = RangeSpread(num_points=10, mean_views=3.0, mean_range=1e-310, spread=0.0)
    for metadata, optical_depth in (
        ({SCALE_KEY: 2.0}, 3.0),
        ({SCALE_KEY: 2.0, RANGE_SPREAD_KEY: spread}, 0.0),
        ({SCALE_KEY: 2.0, RANGE_SPREAD_KEY: degenerate}, 3.0),
    ):
        m = tiny_model(metadata=metadata, medium_init_optical_depth=optical_depth, medium_init_density=0.3)
        sigma = m.medium_field(directions).sigma_attn
        torch.testing.assert_close(sigma, torch.full_like(sigma, 0.3))


def test_training_metrics_carry_the_decomposition_diagnostics(model):
    from seathru_nerfstudio import diagnostics

    model.train()
    out = model(rays(16, seed=6))
    gt_depth = torch.full((16, 1), 1.0)
    gt_depth[:4] = float("inf")
    batch = {"image": torch.rand(16, 3), "gt_depth": gt_depth}
    values = model.get_metrics_dict(out, batch)
    torch.testing.assert_close(values["accumulation_open_water"], out["accumulation"][:4].mean().detach())
    relative = (out["depth"][4:] - 1.0).abs() / 1.0
    torch.testing.assert_close(values["depth_error"], relative.median().detach())
    torch.testing.assert_close(values["medium_beta_D_r"], out["medium_attenuation"][:, 0].mean().detach())
    share = out["backscatter"].sum() / out["rgb"].sum()
    torch.testing.assert_close(values["backscatter_share"], share.detach())
    green = out["direct"][:, 1].sum() / out["rgb"][:, 1].sum()
    torch.testing.assert_close(values["direct_share_g"], green.detach())
    line = diagnostics.format_line(values)
    assert "open water" in line and "depth error" in line and "beta_D" in line and "backscatter share" in line
    assert "direct share" in line


def test_a_dead_colour_channel_is_named_in_the_log_line():
    from seathru_nerfstudio import diagnostics

    values = {f"medium_{n}_{c}": torch.tensor(0.5) for n in ("beta_D", "beta_B", "B_inf") for c in "rgb"}
    values.update(accumulation=torch.tensor(0.8), backscatter_share=torch.tensor(0.9))
    shares = {"r": 0.2, "g": 0.001, "b": 0.1}
    values.update({f"direct_share_{c}": torch.tensor(v) for c, v in shares.items()})
    assert diagnostics.dead_channels(values) == "g"
    assert "DEAD COLOUR CHANNEL g" in diagnostics.format_line(values)
    # a scene that is nearly all backscatter in every channel has no live channel to compare with
    values.update({f"direct_share_{c}": torch.tensor(0.004) for c in "rgb"})
    assert diagnostics.dead_channels(values) == "" and "DEAD" not in diagnostics.format_line(values)
    values.pop("direct_share_b")
    assert diagnostics.dead_channels(values) == ""


def test_medium_first_steps_freeze_the_object_field_only():
    model = tiny_model(medium_first_steps=5, medium_scope="scene")
    model.train()
    for step, frozen in ((0, True), (4, True), (5, False)):
        model.train_step = step
        model.zero_grad()
        out = model(rays(16, seed=7))
        out["rgb"].sum().backward()
        field_grads = [p.grad for p in model.field.parameters() if p.grad is not None and p.grad.abs().sum() > 0]
        assert bool(field_grads) != frozen, step
        rgb_grad = model.medium_field.rgb_logit.grad
        assert rgb_grad is not None and rgb_grad.abs().sum() > 0
        if frozen:  # an empty scene: every ray shows exactly the veiling light
            torch.testing.assert_close(out["rgb"], out["medium_rgb"])
            assert out["accumulation"].abs().max() == 0
    model.eval()
    assert not model.object_frozen  # never outside training


def test_a_learning_oracle_starts_at_the_truth_and_its_medium_learns(tmp_path):
    truth = {"beta_D": [1.3, 1.2, 0.9], "beta_B": [0.95, 0.85, 0.7], "B_inf": [0.07, 0.2, 0.39]}
    (tmp_path / "medium.json").write_text(__import__("json").dumps(truth))
    box = SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    config = tiny_model().config
    config.research.medium_oracle = tmp_path / "medium.json"
    config.research.medium_oracle_learns = True
    model = config.setup(scene_box=box, num_train_data=4, metadata={"dataparser_scale": 2.5})
    model.eval()
    with torch.no_grad():
        out = model(rays(4))
    torch.testing.assert_close(out["medium_attenuation"], torch.tensor([[1.3, 1.2, 0.9]]).expand(4, 3) / 2.5)
    torch.testing.assert_close(out["medium_backscatter"], torch.tensor([[0.95, 0.85, 0.7]]).expand(4, 3) / 2.5)
    torch.testing.assert_close(out["medium_rgb"], torch.tensor([[0.07, 0.2, 0.39]]).expand(4, 3))
    groups = model.get_param_groups()
    assert groups["medium_density"] and groups["medium"]  # it learns, in the groups of a learned medium


def test_the_first_stage_reads_the_open_water_in_its_second_half_and_the_veil_is_held_after_it():
    """With SfM depths: the first stage's second half averages the colour of the rays its geometry leaves
    open (not the first half); after the stage the veil gets no gradient while the densities learn.
    Without depths (an untrained geometry) nothing is read and the veil learns on."""
    torch.manual_seed(0)
    depths = {"depth_filenames": ["frame_00000.png"]}
    model = tiny_model(metadata=depths, medium_scope="scene", medium_first_steps=6, average_init_density=0.01)
    bare = tiny_model(medium_scope="scene", medium_first_steps=6)
    model.train(), bare.train()
    from seathru_nerfstudio.medium_start import is_open_water

    image = torch.rand(16, 3)
    expected_open, expected_total = 0, torch.zeros(3, dtype=torch.float64)
    for step in (0, 2, 3, 5):
        model.train_step = step
        out = model(rays(16, seed=step))
        batch = {"image": image, "depth_image": torch.zeros(16, 1)}
        model.get_loss_dict(out, batch, model.get_metrics_dict(out, batch))
        assert (model.open_water_colour.rays > 0) == (step >= 3), step
        if step >= 3:  # T past the last sample, from the geometry's own outputs
            past = out["transmittance"][..., -1, 0] - out["weights_list"][-1][..., -1, 0]
            expected_open += int(is_open_water(past).sum())
            expected_total += image[is_open_water(past)].double().sum(dim=0)
    assert (model.open_water_colour.rays, model.open_water_colour.open_rays) == (32, expected_open)
    torch.testing.assert_close(model.open_water_colour.total, expected_total)
    for m, held in ((model, True), (bare, False)):
        m.train_step = 6
        m.zero_grad()
        m(rays(16, seed=7))["rgb"].sum().backward()
        veil = m.medium_field.rgb_logit.grad
        assert (veil is None or veil.abs().sum() == 0) == held
        assert m.medium_field.density_raw.grad is not None and m.medium_field.density_raw.grad.abs().sum() > 0
    model.eval()
    assert not model.veil_held  # renders outside training take the viewer's controls


def test_first_stage_geometry_learns_the_density_from_depths_only_and_renders_an_empty_scene(tmp_path):
    truth = {"beta_D": [1.3, 1.2, 0.9], "beta_B": [0.95, 0.85, 0.7], "B_inf": [0.07, 0.2, 0.39]}
    (tmp_path / "medium.json").write_text(__import__("json").dumps(truth))
    for medium in ({"medium_scope": "scene"}, {"medium_oracle": tmp_path / "medium.json"}):
        model = tiny_model(medium_first_steps=5, depth_loss_mult=1.0, **medium)
        model.train()
        model.train_step = 0
        assert model.object_frozen  # a fixed medium too: the geometry learns
        bundle = rays(16, seed=7)
        bundle.metadata["directions_norm"] = torch.ones(16, 1)
        out = model(bundle)
        torch.testing.assert_close(out["rgb"], out["medium_rgb"])  # the image: an empty scene
        assert out["accumulation"].abs().max() == 0
        assert out["weights_list"][-1].sum() > 0  # the geometry the depth loss and proposals see
        # the prior sees the geometry's transmittance: T_0 = 1 and w_i = T_i - T_{i+1}
        weights, transmittance = out["weights_list"][-1], out["transmittance"]
        assert torch.all(transmittance[..., 0, :] == 1) and transmittance.requires_grad
        torch.testing.assert_close(weights[..., :-1, :], transmittance[..., :-1, :] - transmittance[..., 1:, :])
        batch = {"image": torch.rand(16, 3), "depth_image": torch.full((16, 1), 0.6)}
        losses = model.get_loss_dict(out, batch, model.get_metrics_dict(out, batch))
        model.zero_grad()
        sum(losses.values()).backward()
        head = [p for n, p in model.field.named_parameters() if "mlp_head" in n]
        assert head and all(p.grad is None or p.grad.abs().sum() == 0 for p in head)  # colour waits
        base = [p for n, p in model.field.named_parameters() if "mlp_base" in n]
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in base)  # density learns
        if "medium_oracle" in medium:
            # No depth images, on a step where the proposal samplers do not update either: nothing
            # would learn (torch would fail with "does not require grad"); said at once instead.
            with torch.no_grad():
                out = model(bundle)
            no_depth = {"image": batch["image"]}
            with pytest.raises(ValueError, match="medium-first-steps 0"):
                model.get_loss_dict(out, no_depth, model.get_metrics_dict(out, no_depth))


def test_first_stage_without_depth_images_trains_no_geometry():
    """The geometry stage is the default; without SfM depths only the prior would act on the
    geometry, and it would only erase it: the density waits, as the colour does."""
    model = tiny_model(medium_first_steps=5)
    model.train()
    model.train_step = 0
    assert model.object_frozen
    out = model(rays(16, seed=7))
    batch = {"image": torch.rand(16, 3)}
    losses = model.get_loss_dict(out, batch, model.get_metrics_dict(out, batch))
    assert "binary_prior_loss" not in losses and "depth_loss" not in losses
    model.zero_grad()
    sum(losses.values()).backward()
    base = [p for n, p in model.field.named_parameters() if "mlp_base" in n]
    assert base and all(p.grad is None or p.grad.abs().sum() == 0 for p in base)
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.medium_field.parameters())


def test_predict_normals_is_refused_with_a_clear_message():
    with pytest.raises(ValueError, match="predict-normals True is not supported"):
        SeathruModelConfig(predict_normals=True)
    config = tiny_model().config
    config.predict_normals = True  # changed after construction (as overrides do): refused when built
    with pytest.raises(ValueError, match="--normal-method open3d"):
        config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]])), num_train_data=4)


def test_offline_lpips_is_scoped_to_its_block():
    import torchmetrics.image.lpip as lpip_module

    original = lpip_module.LearnedPerceptualImagePatchSimilarity
    with pytest.raises(RuntimeError):
        with metrics.offline_lpips():
            assert lpip_module.LearnedPerceptualImagePatchSimilarity is metrics.make_lpips
            raise RuntimeError("model construction failed")
    assert lpip_module.LearnedPerceptualImagePatchSimilarity is original


def small_camera():
    from nerfstudio.cameras.cameras import Cameras

    c2w = torch.eye(4)[:3][None]
    c2w[0, 2, 3] = 1.5  # outside the box, looking along -z into it
    return Cameras(camera_to_worlds=c2w, fx=12.0, fy=12.0, cx=8.0, cy=6.0, width=16, height=12)


def test_camera_renders_are_linear_and_add_named_display_outputs_first():
    from seathru_nerfstudio.viewer import DISPLAY_OUTPUTS, linear_to_srgb

    torch.manual_seed(0)
    model = tiny_model()
    model.eval()
    out = model.get_outputs_for_camera(small_camera())
    names = list(out)
    assert tuple(names[: len(DISPLAY_OUTPUTS)]) == DISPLAY_OUTPUTS  # the viewer opens on the first: rgb_display
    for name in CONTRACT:  # linear, as every other caller gets them
        assert name in out, name
    with torch.no_grad():
        flat = model(small_camera().generate_rays(camera_indices=0).flatten())
    torch.testing.assert_close(out["rgb"].reshape(-1, 3), flat["rgb"])
    torch.testing.assert_close(out["rgb_display"], linear_to_srgb(out["rgb"]))  # linear data: sRGB display
    torch.testing.assert_close(out["clean_display"], linear_to_srgb(out["clean"]))
    attenuation = out["medium_attenuation_display"]
    torch.testing.assert_close(attenuation, out["medium_attenuation"] / out["medium_attenuation"].max())

    controls = model.viewer_controls
    controls.c1_water.value = False  # Water off: rgb_display is the clean image, rgb stays in the water
    controls.c5_exposure.value = 1.0
    off = model.get_outputs_for_camera(small_camera())
    torch.testing.assert_close(off["rgb_display"], linear_to_srgb(2 * out["clean"]))
    torch.testing.assert_close(off["rgb"], out["rgb"])

    model.train()  # training renders no display outputs
    with torch.no_grad():
        assert not set(DISPLAY_OUTPUTS) & set(model.get_outputs_for_camera_ray_bundle(
            small_camera().generate_rays(camera_indices=0, keep_shape=True)))


def test_water_controls_change_the_medium_outside_training_unless_switched_off():
    torch.manual_seed(0)
    model = tiny_model()
    controls = model.viewer_controls
    bundle = rays(16, seed=8)
    model.eval()
    with torch.no_grad():
        trained = model(bundle)
        controls.c2_density.value = 0.0
        controls.c3_veil_override.value = True
        controls.c4_veil_rgb.value = (255, 0, 0)
        clear = model(bundle)
        model.medium_controls_enabled = False  # what SeathruPipeline does while it evaluates
        evaluated = model(bundle)
        model.medium_controls_enabled = True
        model.train()
        training = model(bundle)
    torch.testing.assert_close(clear["rgb"], clear["clean"])  # density 0: no water at all
    torch.testing.assert_close(clear["medium_rgb"], torch.tensor([[1.0, 0.0, 0.0]]).expand(16, 3))
    for name in ("rgb", "medium_rgb", "medium_attenuation"):
        assert torch.equal(evaluated[name], trained[name]), name
    for name in ("medium_rgb", "medium_attenuation", "medium_backscatter"):  # (training jitters the samples)
        assert torch.equal(training[name], trained[name]), name  # training never sees the controls


def test_fitted_densities_that_are_held_get_no_gradient_and_the_others_learn():
    """After the fit, the channels it replaced get no gradient in training;
    a channel it kept (here green) trains on, as before the fit; also through a tied medium (``fog``
    averages each kind over the channels), where the hold acts on the parameters, not on the tied outputs."""
    for medium_model in ("seathru", "fog"):
        model = tiny_model(medium_first_steps=0, medium_model=medium_model)
        model.train()
        model.train_step = 20
        model.densities_fitted.copy_(torch.tensor([True, False, True, True, False, True]))
        model.zero_grad()
        out = model(rays(16, seed=3))
        (out["rgb"].sum() + out["medium_attenuation"].sum()).backward()
        grad = model.medium_field.density_raw.grad
        assert (grad[[0, 2, 3, 5]] == 0).all() and (grad[[1, 4]].abs() > 0).all(), medium_model


def test_a_zero_or_non_finite_dataparser_scale_is_refused():
    """Densities are converted to 1/m through the scale; 0 would divide by zero later, so it is refused at set-up."""
    from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY

    for scale in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match=SCALE_KEY):
            tiny_model(metadata={SCALE_KEY: scale})
    assert tiny_model(metadata={SCALE_KEY: 0.25}).world_scale == 0.25


def test_a_fit_of_the_same_inputs_is_computed_once():
    """``auto``'s evidence and ``apply_medium_fit`` at the same step fit the same medium: the second
    call returns the first fit; new densities, or another tie, fit again."""
    from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY, SFM_OBSERVATIONS_KEY
    from seathru_nerfstudio.data.sfm_observations import SfmObservations
    from seathru_nerfstudio.medium_fit import fit_model_medium

    rng = np.random.default_rng(0)
    ranges = rng.uniform(1.0, 3.0, (50, 1)) * rng.uniform(0.9, 1.1, (50, 4))
    colours = rng.uniform(0.1, 1.0, (50, 1, 3)) * np.exp(-ranges[..., None]) + 0.3 * -np.expm1(-0.8 * ranges[..., None])
    table = SfmObservations(ranges=ranges, colours=colours)
    model = tiny_model(metadata={SCALE_KEY: 1.0, SFM_OBSERVATIONS_KEY: table})
    first = fit_model_medium(model, table, tie="seathru")[2]
    assert fit_model_medium(model, table, tie="seathru")[2] is first
    assert fit_model_medium(model, table, tie="fog")[2] is not first
    with torch.no_grad():
        model.medium_field.density_raw.add_(0.1)
    again = fit_model_medium(model, table, tie="seathru")[2]
    assert again is not first and torch.allclose(again.attenuation, first.attenuation, rtol=1e-4)  # same data, same optimum


def test_medium_fit_step_sets_the_densities_to_the_fit_of_the_sfm_observations(capsys):
    """At ``medium_fit_step`` the scene medium's densities (per scene unit) are held and move to the fit
    (per metre, divided by the scale) over ``auto_blend_steps``; before that step nothing changes; a
    ray medium is left alone."""
    from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY, SFM_OBSERVATIONS_KEY
    from seathru_nerfstudio.data.sfm_observations import SfmObservations
    from seathru_nerfstudio.medium_fit import fit_model_medium

    rng = np.random.default_rng(0)
    beta_d, beta_b = np.array([1.3, 1.2, 0.9]), np.array([0.95, 0.85, 0.7])
    ranges = rng.uniform(1.0, 3.0, (200, 1)) * rng.uniform(0.9, 1.1, (200, 6))
    colour = rng.uniform(0.1, 1.0, (200, 1, 3))
    table = SfmObservations(ranges=ranges, colours=np.zeros((200, 6, 3)))  # colours set below, under the model's veil
    m = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}, medium_fit_step=10, medium_first_steps=5, auto_blend_steps=4)
    veil = torch.sigmoid(m.medium_field.rgb_logit.detach().double()).numpy()
    table.colours[...] = colour * np.exp(-beta_d * ranges[..., None]) + veil * -np.expm1(-beta_b * ranges[..., None])
    before = m.medium_field.density_raw.detach().clone()
    apply_medium_fit(m, 5)
    torch.testing.assert_close(m.medium_field.density_raw.detach(), before)
    apply_medium_fit(m, 9)
    # held from the fit on, the densities move to it in log space over auto_blend_steps (4 here)
    torch.testing.assert_close(m.medium_field.density_raw.detach(), before)
    assert m.densities_fitted.all()
    start = torch.nn.functional.softplus(before.double())
    apply_medium_fit(m, 11)  # half way: the geometric mean of the start and the fit
    halfway = torch.nn.functional.softplus(m.medium_field.density_raw.detach().double())
    torch.testing.assert_close(halfway, torch.sqrt(start * torch.tensor([*beta_d, *beta_b]) / 2.0), rtol=0.01, atol=0)
    resumed = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}, medium_fit_step=10, medium_first_steps=5, auto_blend_steps=4)
    resumed.load_state_dict(m.state_dict())  # a checkpoint half way moves on alike
    apply_medium_fit(m, 12), apply_medium_fit(resumed, 12)
    assert torch.equal(resumed.medium_field.density_raw.detach(), m.medium_field.density_raw.detach())
    apply_medium_fit(m, 13)
    sigma = torch.nn.functional.softplus(m.medium_field.density_raw.detach().double())
    torch.testing.assert_close(sigma * 2.0, torch.tensor([*beta_d, *beta_b]), rtol=0.01, atol=0)
    apply_medium_fit(m, 14)  # the ramp is over: nothing moves
    assert torch.equal(torch.nn.functional.softplus(m.medium_field.density_raw.detach().double()), sigma)
    # a channel whose fit error exceeds the bound keeps its trained densities however far they lie
    # from the fit (noisy colours give errors of 0.2-0.6 in ln beta_D here); the others are replaced
    noisy = SfmObservations(ranges=ranges, colours=table.colours + rng.normal(0.0, 0.02, table.colours.shape))
    strict = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: noisy}, medium_fit_step=10, medium_first_steps=5)
    _, _, fit = fit_model_medium(strict, noisy, tie="seathru")
    errors = fit.attenuation_log_error
    assert (errors > 0.01).all() and errors.unique().numel() == 3
    bound = float((errors.median() * errors.max()).sqrt())  # between the two least precise channels
    strict.config.research.medium_fit_max_log_error = bound
    precise = errors <= bound
    trained = torch.cat([fit.attenuation, fit.backscatter]) / 2.0
    trained[:3][~precise] *= torch.exp(4.0 * errors[~precise])  # far outside the fit's interval: still kept
    strict.medium_field.set_densities(trained)
    kept = strict.medium_field.density_raw.detach().clone()
    apply_medium_fit(strict, 9)
    apply_medium_fit(strict, 9 + strict.config.research.auto_blend_steps)  # to the end of the ramp
    assert strict.densities_fitted.tolist() == [*precise.tolist(), *precise.tolist()]
    imprecise = torch.cat([~precise, ~precise])
    torch.testing.assert_close(strict.medium_field.density_raw.detach()[imprecise], kept[imprecise])  # these train on
    sigma = torch.nn.functional.softplus(strict.medium_field.density_raw.detach().double())[:3] * 2.0
    torch.testing.assert_close(sigma[precise], fit.attenuation[precise], rtol=1e-3, atol=0)
    with pytest.raises(ValueError, match="medium-fit-max-log-error"):
        tiny_model(medium_fit_max_log_error=float("nan"))
    # the fitted channels are held; the hold and the fit's errors survive a checkpoint
    assert m.densities_fitted.all() and (m.fit_log_error >= 0).all()
    held = m
    reloaded = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}, medium_fit_step=10, medium_first_steps=5)
    reloaded.load_state_dict(held.state_dict())
    assert reloaded.densities_fitted.all() and torch.equal(reloaded.fit_log_error, held.fit_log_error)
    # the fit ties the densities as the medium model in use renders them; clear air has none to fit
    fog = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}, medium_fit_step=10, medium_first_steps=5, medium_model="fog")
    capsys.readouterr()
    apply_medium_fit(fog, 9)
    assert "(fog tie)" in capsys.readouterr().out  # the log names the tie it fitted
    apply_medium_fit(fog, 9 + fog.config.research.auto_blend_steps)
    fog_sigma = torch.nn.functional.softplus(fog.medium_field.density_raw.detach().double())
    torch.testing.assert_close(fog_sigma[:3], fog_sigma[:1].expand(3), rtol=1e-6, atol=0)  # one grey attenuation
    torch.testing.assert_close(fog_sigma[3:], fog_sigma[3:4].expand(3), rtol=1e-6, atol=0)  # one grey backscatter
    assert not torch.allclose(fog_sigma, torch.nn.functional.softplus(before.double()))
    clear = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}, medium_fit_step=10, medium_first_steps=5, medium_model="none")
    clear_before = clear.medium_field.density_raw.detach().clone()
    apply_medium_fit(clear, 9)
    assert torch.equal(clear.medium_field.density_raw.detach(), clear_before)
    # a medium of the ray direction is not fitted (an MLP, not constants)
    ray = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}, medium_fit_step=10, medium_first_steps=5, medium_scope="ray")
    assert not ray.fits_medium
    state = {k: v.clone() for k, v in ray.state_dict().items()}
    apply_medium_fit(ray, 9)
    assert all(torch.equal(state[k], v) for k, v in ray.state_dict().items())


@pytest.mark.parametrize("parts", ["both", "attenuation", "backscatter"])
def test_the_fit_oracle_puts_the_chosen_true_densities_in_place_of_the_fit_and_holds_them(tmp_path, parts):
    """``medium_fit_oracle``: at ``medium_fit_step`` the chosen true densities (per metre, divided by
    the scale) replace the fit's, the others are the fit's, and all are held; refused without a fit step."""
    from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY, SFM_OBSERVATIONS_KEY
    from seathru_nerfstudio.data.sfm_observations import SfmObservations

    rng = np.random.default_rng(1)
    beta_d, beta_b = np.array([1.3, 1.2, 0.9]), np.array([0.95, 0.85, 0.7])
    ranges = rng.uniform(1.0, 3.0, (200, 1)) * rng.uniform(0.9, 1.1, (200, 6))
    table = SfmObservations(ranges=ranges, colours=np.zeros((200, 6, 3)))
    truth = {"beta_D": [0.5, 0.6, 0.7], "beta_B": [0.2, 0.3, 0.4], "B_inf": [0.1, 0.2, 0.3]}  # not what the table says
    (tmp_path / "medium.json").write_text(json.dumps(truth))
    settings = {"medium_fit_step": 10, "medium_first_steps": 5, "medium_fit_oracle": tmp_path / "medium.json", "medium_fit_oracle_parts": parts}
    m = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}, **settings)
    veil = torch.sigmoid(m.medium_field.rgb_logit.detach().double()).numpy()
    table.colours[...] = rng.uniform(0.1, 1.0, (200, 1, 3)) * np.exp(-beta_d * ranges[..., None]) + veil * -np.expm1(
        -beta_b * ranges[..., None]
    )
    apply_medium_fit(m, 9)
    apply_medium_fit(m, 9 + m.config.research.auto_blend_steps)  # the end of the ramp to them
    per_metre = torch.nn.functional.softplus(m.medium_field.density_raw.detach().double()) * 2.0
    expected_d = truth["beta_D"] if parts != "backscatter" else beta_d
    expected_b = truth["beta_B"] if parts != "attenuation" else beta_b
    torch.testing.assert_close(per_metre, torch.tensor([*expected_d, *expected_b], dtype=torch.float64), rtol=0.01, atol=0)
    assert m.densities_fitted.all()
    with pytest.raises(ValueError, match="medium-fit-oracle"):
        tiny_model(medium_fit_step=None, medium_fit_oracle=tmp_path / "medium.json")
    # a file that is not a medium fails when the model is built, naming the file, not at the fit step
    (tmp_path / "bad.json").write_text(json.dumps({"beta_D": [1.0, 2.0]}))
    for bad in (tmp_path / "bad.json", tmp_path / "missing.json"):
        with pytest.raises(ValueError, match=bad.name):
            tiny_model(medium_fit_step=10, medium_first_steps=5, medium_fit_oracle=bad)


@pytest.mark.parametrize(
    "settings, option",
    [
        ({"binary_prior_early_mult": float("nan")}, "binary-prior-early-mult"),
        ({"binary_prior_early_mult": -1e-3}, "binary-prior-early-mult"),
        ({"backscatter_excess_steps": -1}, "backscatter-excess-steps"),
        ({"medium_fit_step": -5}, "medium-fit-step"),
        ({"medium_fit_step": 100, "medium_first_steps": 200}, "medium-fit-step"),
        ({"medium_first_steps": -1}, "medium-first-steps"),
        ({"binary_prior_mult": float("nan")}, "binary-prior-mult"),
        ({"medium_oracle": "/nonexistent/medium.json"}, "medium-oracle: /nonexistent/medium.json does not exist"),
    ],
)
def test_settings_that_cannot_train_are_refused_naming_the_option(settings, option):
    with pytest.raises(ValueError, match=option):
        tiny_model(**settings)


def test_the_model_measures_elevations_along_the_datas_vertical():
    """The dataparser's vertical reaches the scene medium and the open-water sums' ``direction_up``."""
    from seathru_nerfstudio.metadata_keys import VERTICAL_KEY

    tilted = tiny_model(metadata={VERTICAL_KEY: [0.0, 0.6, 0.8]}).train()
    bundle = rays(32)
    out = tilted(bundle)
    expected = bundle.directions @ torch.tensor([0.0, 0.6, 0.8])
    assert torch.allclose(tilted.medium_field.vertical, torch.tensor([0.0, 0.6, 0.8]))
    assert torch.allclose(out["direction_up"][..., 0], expected, atol=1e-6)
    plain = tiny_model().train()  # no vertical in the metadata: scene +z, nerfstudio's "up"
    assert torch.allclose(plain(bundle)["direction_up"][..., 0], bundle.directions[..., 2], atol=1e-6)
