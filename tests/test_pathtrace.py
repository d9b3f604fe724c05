"""seathru-pathtrace: the physically rendered scenes (Mitsuba 3), their ground truth and layout.

Tiny renders (32x24 px, a few samples per pixel): what is checked are limits and identities
that hold whatever the noise, with the noise measured by a second seed where it matters."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest

from seathru_nerfstudio.data.pathtrace.align import Similarity, umeyama
from seathru_nerfstudio.data.pathtrace.cli import GENERATOR_VERSION, REGISTRATION_VERSION, PathtraceConfig, generate
from seathru_nerfstudio.data.pathtrace.presets import HOLDOUT_EVERY, PRESETS
from seathru_nerfstudio.data.pathtrace.render import OPEN_WATER_ID, PathtraceError, Renderer
from seathru_nerfstudio.data.pathtrace.scene import make_layout, sensor_dict
from seathru_nerfstudio.data.pathtrace.truth import fit_veil_and_backscatter
from seathru_nerfstudio.data.synthetic.cameras import pixel_rays

W, H = 32, 24


def test_fit_recovers_the_formula_parameters():
    """Images drawn from I = J e^{-bD z} + B (1 - e^{-bB z}) give back B and bB (with noise)."""
    rng = np.random.default_rng(0)
    beta_d, beta_b, b_inf = np.array([0.3, 0.17, 0.12]), np.array([0.45, 0.25, 0.2]), np.array([0.05, 0.2, 0.3])
    images, clean, ranges = [], [], []
    for _ in range(4):
        z = rng.uniform(1.5, 12.0, size=(20, 30))
        z[:4] = np.inf  # open water rows
        j = rng.uniform(0.05, 0.8, size=(20, 30, 3))
        finite = np.where(np.isfinite(z), z, 0.0)[..., None]
        image = j * np.exp(-beta_d * finite) - b_inf * np.expm1(-beta_b * finite) + rng.normal(0, 0.002, (20, 30, 3))
        image[:4] = b_inf
        images.append(image)
        clean.append(np.where(np.isfinite(z)[..., None], j, 0.0))
        ranges.append(z)
    fit = fit_veil_and_backscatter(images, clean, ranges, beta_d)
    np.testing.assert_allclose(fit["beta_B"], beta_b, rtol=0.05)
    np.testing.assert_allclose(fit["B_inf"], b_inf, rtol=0.02)
    np.testing.assert_allclose(fit["open_water_mean"], b_inf, rtol=1e-9)
    assert fit["num_pixels"] == 4 * 16 * 30
    with pytest.raises(ValueError, match="finite range"):
        fit_veil_and_backscatter([images[0]], [clean[0]], [np.full((20, 30), np.inf)], beta_d)


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation = q * np.sign(np.linalg.det(q))
    truth = Similarity(2.5, rotation, np.array([1.0, -2.0, 0.5]))
    source = rng.normal(size=(10, 3))
    fit = umeyama(source, truth.apply_points(source))
    assert fit.scale == pytest.approx(2.5, rel=1e-9)
    np.testing.assert_allclose(fit.rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(fit.translation, truth.translation, atol=1e-9)


@pytest.fixture(scope="module")
def coastal():
    preset = PRESETS["coastal"]
    layout = make_layout(0, 3, preset)
    renderer = Renderer(layout, preset, W, H, spp=8)
    yield renderer, layout
    renderer.close()


def test_sensor_rays_are_the_dataset_pinhole(coastal):
    """Mitsuba's pixel-centre rays are the rays of the pose and intrinsics written to the dataset."""
    renderer, layout = coastal
    mi = renderer.mi
    c2w = layout.poses[1]
    sensor = mi.load_dict(sensor_dict(mi, c2w, W, H, 1))
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), mi.Point2f(mi.Float((u / W).ravel()), mi.Float((v / H).ravel())), mi.Point2f(0.5, 0.5))
    mitsuba_dirs = np.array(ray.d).reshape(3, -1).T if np.array(ray.d).shape[0] == 3 else np.array(ray.d)
    ours = pixel_rays(c2w, renderer.K, u, v).reshape(-1, 3)
    assert np.max(np.linalg.norm(mitsuba_dirs - ours, axis=1)) < 1e-4


def test_geometry_ground_truth(coastal):
    """Open water exactly where the range is inf; z-depth = range x cos(angle to the axis)."""
    renderer, layout = coastal
    view = renderer.render(layout.poses[0], seed=0)
    open_water = view.ids == OPEN_WATER_ID
    assert open_water.any() and (~open_water).any()
    assert np.array_equal(open_water, np.isinf(view.range))
    assert np.all(np.isfinite(view.range[~open_water])) and np.all(view.range[~open_water] > 0)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    cos = 1.0 / np.sqrt(((u - renderer.K["cx"]) / renderer.K["fl_x"]) ** 2 + ((v - renderer.K["cy"]) / renderer.K["fl_y"]) ** 2 + 1.0)
    np.testing.assert_allclose(view.z_depth[~open_water], (view.range * cos)[~open_water], rtol=1e-5)
    assert np.all(view.clean[open_water] == 0.0)


def test_same_seed_same_render_other_seed_other_noise(coastal):
    renderer, layout = coastal
    a = renderer.render_mode("medium", layout.poses[2], seed=5)
    b = renderer.render_mode("medium", layout.poses[2], seed=5)
    c = renderer.render_mode("medium", layout.poses[2], seed=6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_clean_is_brighter_than_the_image_on_far_objects(coastal):
    """In water the red signal of far objects is mostly absorbed, and little red backscatter
    replaces it: J (unattenuated towards the camera) exceeds I there."""
    renderer, layout = coastal
    view = renderer.render(layout.poses[1], seed=3)
    known = np.isfinite(view.range)
    far = known & (view.range >= np.quantile(view.range[known], 2.0 / 3.0))
    assert view.clean[far][:, 0].mean() > 1.5 * view.image[far][:, 0].mean()


def test_vanishing_medium_gives_the_medium_free_render():
    """sigma_t -> 0: the in-medium image, J and the medium-free render agree up to Monte Carlo
    noise (measured as the difference between two seeds of the medium-free render)."""
    preset = dataclasses.replace(PRESETS["coastal"], sigma_t=(1e-6, 1e-6, 1e-6))
    layout = make_layout(0, 1, preset)
    renderer = Renderer(layout, preset, W, H, spp=16)
    try:
        c2w = layout.poses[0]
        image, clean, dry_a, dry_b = (renderer.render_mode(m, c2w, seed=s) for m, s in (("medium", 1), ("clean", 2), ("dry", 3), ("dry", 4)))
        _, ids = renderer.cast(c2w)
    finally:
        renderer.close()
    objects = ids != OPEN_WATER_ID
    noise = np.abs(dry_a - dry_b)[objects].mean()
    for other in (image, clean):
        assert np.abs(other - dry_a)[objects].mean() < 1.3 * noise
        np.testing.assert_allclose(other[objects].mean(0), dry_a[objects].mean(0), rtol=0.05)


def test_scene_folder_layout_and_cache(tmp_path):
    """The dataset layout seathru-synth writes (frames' gt fields, medium.json), the holdout,
    and a second run with the same options reusing the folder."""
    config = PathtraceConfig(preset="fog", output_dir=tmp_path / "fog", width=W, height=H, num_views=9, spp=2, poses="truth")
    out = generate(config)
    transforms = json.loads((out / "transforms.json").read_text())
    assert len(transforms["frames"]) == 9
    for frame in transforms["frames"]:
        for field in ("file_path", "depth_file_path", "gt_clean_file_path", "gt_depth_file_path", "gt_dry_file_path", "gt_z_depth_file_path", "gt_ids_file_path"):
            assert (out / frame[field]).is_file(), field
    held = [f"images/frame_{i:05d}.png" for i in range(0, 9, HOLDOUT_EVERY)]
    assert transforms["test_filenames"] == held and len(transforms["train_filenames"]) == 9 - len(held)
    medium = json.loads((out / "ground_truth" / "medium.json").read_text())
    assert medium["beta_D"] == list(PRESETS["fog"].sigma_t)
    assert all(np.isfinite(medium[k]).all() and len(medium[k]) == 3 for k in ("beta_B", "B_inf"))
    stamp = (out / "scene.json").stat().st_mtime_ns
    assert generate(config) == out and (out / "scene.json").stat().st_mtime_ns == stamp


def test_structure_from_motion_that_fails_keeps_the_renders_and_says_why_once(tmp_path, monkeypatch):
    """Where our SfM cannot register the views (4 noisy 32x24 renders), the command raises one
    error naming the images and what SfM said, runs SfM once (it is repeatable, so a second run
    would say the same), and keeps the renders without ``transforms.json`` for ``--poses truth``."""
    import seathru_nerfstudio.data.process as process_module

    calls = []
    real_process = process_module.process
    monkeypatch.setattr(process_module, "process", lambda config: calls.append(config) or real_process(config))
    config = PathtraceConfig(preset="fog", output_dir=tmp_path / "fog", width=W, height=H, num_views=4, spp=2, poses="sfm")
    with pytest.raises(PathtraceError, match="structure from motion") as raised:
        generate(config)
    assert len(calls) == 1 and calls[0].camera_model == "SIMPLE_PINHOLE"  # the renderer's camera
    assert "\n" not in str(raised.value) and "images" in str(raised.value)
    out = config.folder()
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"frame_{i:05d}.png" for i in range(4)]
    assert not (out / "transforms.json").exists()
    record = json.loads((out / "scene.json").read_text())
    assert record["options_hash"] is None and str(raised.value).startswith(record["registration"]["failed"])
    assert "--poses truth" in str(raised.value)
    assert not any(p.name.startswith("_sfm") for p in out.rglob("*"))
    truth = generate(dataclasses.replace(config, poses="truth"))  # the renders are reused for the true poses
    assert (truth / "transforms.json").is_file()


def test_the_sfm_camera_model_is_a_pose_option_that_reuses_the_renders():
    """Another SfM camera model names another scene (the cache key) made from the same renders (the
    render key), so ``--sfm-camera-model`` re-registers a cached scene without rendering it again."""
    simple = PathtraceConfig(preset="coastal")
    other = dataclasses.replace(simple, sfm_camera_model="PINHOLE")
    assert simple.cache_key() != other.cache_key()
    assert simple.cache_key(renders_only=True) == other.cache_key(renders_only=True)


def test_a_new_registration_version_registers_cached_scenes_again_from_their_renders(monkeypatch):
    """When the SfM code would register the same renders otherwise (``REGISTRATION_VERSION``), a
    cached scene's key no longer matches but its renders' key does: it is registered again, not
    rendered again."""
    from seathru_nerfstudio.data.pathtrace import cli

    config = PathtraceConfig(preset="fog")
    key, render_key = config.cache_key(), config.cache_key(renders_only=True)
    monkeypatch.setattr(cli, "REGISTRATION_VERSION", cli.REGISTRATION_VERSION + 1)
    assert config.cache_key() != key
    assert config.cache_key(renders_only=True) == render_key


def test_the_presets_sample_count_is_the_default_and_noise_falls_as_its_root():
    """``--spp`` unset renders at the preset's count (the cache key says so: the same as spelling
    it out, other than another count), and the Monte Carlo noise, the difference between two
    seeds, falls as 1/sqrt(spp): 4x the samples, half the noise."""
    turbid = PathtraceConfig(preset="turbid")
    assert turbid.samples_per_pixel() == PRESETS["turbid"].spp > PRESETS["coastal"].spp
    assert turbid.cache_key() == dataclasses.replace(turbid, spp=PRESETS["turbid"].spp).cache_key()
    assert turbid.cache_key() != dataclasses.replace(turbid, spp=PRESETS["coastal"].spp).cache_key()
    preset = PRESETS["turbid"]
    layout = make_layout(0, 1, preset)
    noise = {}
    for spp in (4, 16):
        renderer = Renderer(layout, preset, W, H, spp=spp)
        a, b = (renderer.render_mode("medium", layout.poses[0], seed) for seed in (1, 2))
        renderer.close()
        noise[spp] = np.std(a - b) / np.mean(a + b)
    assert noise[4] / noise[16] == pytest.approx(2.0, rel=0.25)


def test_bad_options_fail_in_one_line(tmp_path):
    with pytest.raises(PathtraceError, match="unknown preset 'reef'"):
        generate(PathtraceConfig(preset="reef", output_dir=tmp_path / "x"))
    with pytest.raises(PathtraceError, match="--spp"):
        generate(PathtraceConfig(spp=0, output_dir=tmp_path / "x"))
    result = subprocess.run(
        [sys.executable, "-m", "seathru_nerfstudio.data.pathtrace.cli", "--preset", "reef", "--output-dir", str(tmp_path / "y")],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 1
    lines = [line for line in (result.stdout + result.stderr).splitlines() if line.strip()]
    assert len(lines) == 1 and "unknown preset 'reef'" in lines[0]
    assert not (tmp_path / "y").exists()


def test_the_sun_options_replace_the_presets_sun_and_name_other_renders(tmp_path):
    """``--sun-elevation-deg`` / ``--sun-azimuth-deg`` replace the preset's sun (and only it), enter the
    renders' key, and leave the key of a scene that does not give them (nor ``--sfm-focal-prior``) as it was."""
    from seathru_nerfstudio.data.pathtrace.scene import sun_direction

    default = PathtraceConfig(preset="coastal", seed=8)
    assert default.preset_used() == PRESETS["coastal"]
    low = dataclasses.replace(default, sun_elevation_deg=45.0, sun_azimuth_deg=100.0)
    assert low.preset_used() == dataclasses.replace(PRESETS["coastal"], sun_elevation_deg=45.0, sun_azimuth_deg=100.0)
    assert low.cache_key(renders_only=True) != default.cache_key(renders_only=True)
    overhead = dataclasses.replace(default, sun_elevation_deg=90.0).preset_used()
    assert np.allclose(sun_direction(overhead), [0.0, 1.0, 0.0])
    keys = {k for k in dataclasses.asdict(default) if k not in ("output_dir", "overwrite", "variant")}
    assert default.cache_key() == hashlib.sha256(json.dumps(
        {**{k: dataclasses.asdict(default)[k] for k in keys - {"sun_elevation_deg", "sun_azimuth_deg", "sfm_focal_prior"}},
         "spp": default.samples_per_pixel(), "generator_version": GENERATOR_VERSION, "registration_version": REGISTRATION_VERSION},
        sort_keys=True, default=str).encode()).hexdigest()[:16]  # fmt: skip
    for bad in (0.0, -10.0, 91.0, float("nan")):
        with pytest.raises(PathtraceError, match="--sun-elevation-deg"):
            generate(PathtraceConfig(sun_elevation_deg=bad, output_dir=tmp_path / "x"))
    with pytest.raises(PathtraceError, match="--sun-azimuth-deg"):
        generate(PathtraceConfig(sun_azimuth_deg=float("inf"), output_dir=tmp_path / "x"))
    assert not (tmp_path / "x").exists()


def test_the_focal_prior_is_a_pose_option_at_the_renderers_focal_length():
    """``--sfm-focal-prior`` gives SfM the pinhole focal length of the renderer's field of view; it reuses
    the renders, and a scene that does not ask for it keeps its key."""
    from seathru_nerfstudio.data.pathtrace.cli import _prior_focal
    from seathru_nerfstudio.data.synthetic.cameras import HORIZONTAL_FOV_DEG

    plain = PathtraceConfig(preset="clear", seed=6, width=W, height=H)
    prior = dataclasses.replace(plain, sfm_focal_prior=True)
    assert _prior_focal(plain) is None
    half_width = W / 2 / _prior_focal(prior)  # tan of half the horizontal field of view
    assert np.degrees(2 * np.arctan(half_width)) == pytest.approx(HORIZONTAL_FOV_DEG)
    assert prior.cache_key(renders_only=True) == plain.cache_key(renders_only=True)
    assert prior.cache_key() != plain.cache_key()


def test_sun_disc_carries_the_sun_irradiance():
    """A finite sun in the sky map: its radiance times the texels' solid angle is the irradiance
    the preset gives, and it sits around the sun's direction."""
    from seathru_nerfstudio.data.pathtrace.scene import sky_bitmap, sun_direction

    preset = dataclasses.replace(PRESETS["coastal"], sun_radius_deg=4.0)
    without = dataclasses.replace(preset, sun_radius_deg=0.0)
    height = 128
    extra = sky_bitmap(preset, height) - sky_bitmap(without, height)
    theta = np.pi * (np.arange(height) + 0.5) / height
    texel = (np.pi / height) * (np.pi / height) * np.sin(theta)[:, None, None]
    np.testing.assert_allclose((extra * texel).sum(axis=(0, 1)), preset.sun_irradiance, rtol=1e-5)
    row, col = np.unravel_index(np.argmax(extra[..., 1] * texel[..., 0]), extra.shape[:2])
    u, v = (col + 0.5) / (2 * height), (row + 0.5) / height
    d = np.array([np.sin(np.pi * v) * np.sin(2 * np.pi * u), np.cos(np.pi * v), -np.sin(np.pi * v) * np.cos(2 * np.pi * u)])
    assert np.degrees(np.arccos(np.clip(d @ sun_direction(preset), -1, 1))) < 4.0
