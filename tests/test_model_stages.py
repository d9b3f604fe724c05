"""SeathruModel through its training timeline: the medium's start from the SfM range, the first stage
(veiling light and SfM geometry, the object field frozen), the open water read at its end, the medium
fit and the densities it holds, and the oracles that stand in for them."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nerfstudio.data.scene_box import SceneBox

from seathru_nerfstudio.medium_fit import apply_medium_fit, fit_model_medium

from tiny_training import rays, tiny_model


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


@pytest.mark.parametrize("learns", [False, True])
def test_an_oracle_medium_is_the_truth_per_scene_unit(tmp_path, learns):
    """``research.medium_oracle``: the true medium (1/m, divided by the scene units per metre) in place
    of the learned one; held (no parameters), or a start that learns on (``medium_oracle_learns``)."""
    truth = {"beta_D": [1.3, 1.2, 0.9], "beta_B": [0.95, 0.85, 0.7], "B_inf": [0.07, 0.2, 0.39]}
    (tmp_path / "medium.json").write_text(json.dumps(truth))
    box = SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    config = tiny_model().config
    config.research.medium_oracle = tmp_path / "medium.json"
    config.research.medium_oracle_learns = learns
    model = config.setup(scene_box=box, num_train_data=4, metadata={"dataparser_scale": 2.5})
    model.eval()
    with torch.no_grad():
        out = model(rays(4))
    # 1/m divided by 2.5 scene units per metre
    torch.testing.assert_close(out["medium_attenuation"], torch.tensor([[1.3, 1.2, 0.9]]).expand(4, 3) / 2.5)
    torch.testing.assert_close(out["medium_backscatter"], torch.tensor([[0.95, 0.85, 0.7]]).expand(4, 3) / 2.5)
    torch.testing.assert_close(out["medium_rgb"], torch.tensor([[0.07, 0.2, 0.39]]).expand(4, 3))
    groups = model.get_param_groups()
    if learns:
        assert groups["medium_density"] and groups["medium"]  # in the groups of a learned medium
    else:
        assert "medium" not in groups and "medium_density" not in groups
        assert config.medium_model == "seathru"  # the default auto has nothing to choose with an oracle


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


def test_a_fit_of_the_same_inputs_is_computed_once():
    """``auto``'s evidence and ``apply_medium_fit`` at the same step fit the same medium: the second
    call returns the first fit; new densities, or another tie, fit again."""
    from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY, SFM_OBSERVATIONS_KEY
    from seathru_nerfstudio.data.sfm_observations import SfmObservations

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
    assert m.densities_fitted.all() and (m.fit_log_error >= 0).all() and (m.fit_backscatter_log_error >= 0).all()
    assert torch.all(m.backscatter_veil_sensitivity < 0)  # a brighter veil, a smaller beta_B
    held = m
    reloaded = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}, medium_fit_step=10, medium_first_steps=5)
    reloaded.load_state_dict(held.state_dict())
    assert reloaded.densities_fitted.all() and torch.equal(reloaded.fit_log_error, held.fit_log_error)
    assert torch.equal(reloaded.fit_backscatter_log_error, held.fit_backscatter_log_error)
    assert torch.equal(reloaded.backscatter_veil_sensitivity, held.backscatter_veil_sensitivity)
    # the fit ties the densities as the medium model in use renders them; clear air has none to fit
    fog = tiny_model(metadata={SCALE_KEY: 2.0, SFM_OBSERVATIONS_KEY: table}, medium_fit_step=10, medium_first_steps=5, medium_model="fog")
    capsys.readouterr()
    apply_medium_fit(fog, 9)
    assert "(fog tie)" in capsys.readouterr().out  # the log names the tie it fitted
    apply_medium_fit(fog, 9 + fog.config.research.auto_blend_steps)
    fog_sigma = torch.nn.functional.softplus(fog.medium_field.density_raw.detach().double())
    torch.testing.assert_close(fog_sigma[:3], fog_sigma[:1].expand(3), rtol=1e-6, atol=0)  # one grey attenuation
    fitted_free = fit_model_medium(fog, table, tie="seathru")[2]  # this table's medium is coloured (water)
    assert not torch.allclose(fitted_free.backscatter, fitted_free.backscatter[:1].expand(3), rtol=1e-3)
    assert not torch.allclose(fog_sigma[3:], fog_sigma[3:4].expand(3), rtol=1e-3)  # the backscatter per channel
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
