"""SeathruModel glue: outputs contract, per-ray medium, offline LPIPS, metrics, checkpoints, camera renders
and settings (its losses: test_model_losses.py; its training stages: test_model_stages.py)."""

from __future__ import annotations

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
from seathru_nerfstudio.losses import rawnerf_loss
from seathru_nerfstudio.medium_field import MEDIUM_MODELS
from seathru_nerfstudio.model import SeathruModel, SeathruModelConfig

from tiny_training import rays, seeded_tiny_model, spy_calls, tiny_model

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


@pytest.fixture(scope="module")
def model() -> SeathruModel:
    return seeded_tiny_model()


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


def object_colour_by_direction(model) -> torch.Tensor:
    """The object field's colour at two fixed points seen along three directions, ``(3, 2, 3)``."""
    model.eval()
    positions = torch.tensor([[0.1, 0.2, -0.3], [0.0, -0.1, 0.2]])
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
    return torch.stack(per_direction)


def depends_on_direction(colours: torch.Tensor) -> bool:
    """Whether the colours of :func:`object_colour_by_direction` change with the direction (else they are equal)."""
    if (colours - colours[:1]).abs().max() > 1e-4:
        return True
    torch.testing.assert_close(colours, colours[:1].expand_as(colours))
    return False


def test_lambertian_object_colour_does_not_depend_on_the_view_direction():
    torch.manual_seed(0)
    lambertian = tiny_model(object_view_dependent=False, medium_model="none")
    torch.manual_seed(0)
    glossy = tiny_model(object_view_dependent=True, medium_model="seathru")
    assert not depends_on_direction(object_colour_by_direction(lambertian))
    assert depends_on_direction(object_colour_by_direction(glossy))  # the switch is what makes the difference


def test_the_object_colour_is_lambertian_in_a_medium_and_view_dependent_in_clear_air():
    for medium_model in ("seathru", "fog", "auto"):  # auto: seathru until it decides
        assert not depends_on_direction(object_colour_by_direction(tiny_model(medium_model=medium_model)))
    assert depends_on_direction(object_colour_by_direction(tiny_model(medium_model="none")))
    chosen = tiny_model(medium_model="auto")  # as auto's decision sets it, and as a checkpoint of it loads
    chosen.medium_model_code.fill_(MEDIUM_MODELS.index("none"))
    chosen.fit_object_field_to_medium_model()
    assert depends_on_direction(object_colour_by_direction(chosen))
    loaded = tiny_model(medium_model="auto")
    loaded.load_state_dict(chosen.state_dict())
    assert depends_on_direction(object_colour_by_direction(loaded))


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


def test_a_zero_or_non_finite_dataparser_scale_is_refused():
    """Densities are converted to 1/m through the scale; 0 would divide by zero later, so it is refused at set-up."""
    from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY

    for scale in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match=SCALE_KEY):
            tiny_model(metadata={SCALE_KEY: scale})
    assert tiny_model(metadata={SCALE_KEY: 0.25}).world_scale == 0.25


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
