"""Poses: seathru-process-data's pycolmap path on a rendered underwater scene, checked
against the generator's ground-truth cameras after a similarity (Umeyama) alignment."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2  # before pycolmap (see seathru_nerfstudio/data/sfm.py)
import numpy as np
import pytest

from seathru_nerfstudio.data.io import write_png16
from seathru_nerfstudio.data.process import ProcessReport, ProcessSeathruData, process
from seathru_nerfstudio.data.sfm_images import display_transform, feature_image
from seathru_nerfstudio.data.synthetic import SynthConfig, generate


NUM_VIEWS = 16
DISTRACTORS = ["zz_unrelated_0.png", "zz_unrelated_1.png"]


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising ||s R source + t - target||² (Umeyama 1991)."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    u, d, vt = np.linalg.svd(xt.T @ xs / len(source))
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rotation = u @ sign @ vt
    scale = np.trace(np.diag(d) @ sign) / (xs**2).sum(1).mean()
    return scale, rotation, mu_t - scale * rotation @ mu_s


def c2w_by_name(transforms: Path) -> dict[str, np.ndarray]:
    frames = json.loads(transforms.read_text())["frames"]
    return {Path(f["file_path"]).name: np.asarray(f["transform_matrix"], dtype=np.float64) for f in frames}


@pytest.fixture(scope="module")
def sfm_run(tmp_path_factory) -> tuple[Path, Path, ProcessReport, dict[str, str]]:
    """Render a water scene (16 views, 320×240), add two unrelated frames that cannot
    register, run the full pipeline once for every test in this module."""
    root = tmp_path_factory.mktemp("sfm")
    scene = generate(SynthConfig(output_dir=root / "scene", preset="water", seed=0, width=320, height=240, num_views=NUM_VIEWS))
    rng = np.random.default_rng(0)
    for name in DISTRACTORS:  # a blurred-noise texture seen nowhere else
        noise = cv2.GaussianBlur(rng.uniform(0, 0.4, (240, 320, 3)).astype(np.float32), (0, 0), 2.0)
        write_png16(scene / "images" / name, noise)
    inputs = scene / "images"
    before = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in inputs.iterdir()}
    report = process(ProcessSeathruData(data=inputs, output_dir=root / "dataset"))
    return scene, root / "dataset", report, before


def test_display_transform_lifts_dark_linear_frames() -> None:
    dark = np.linspace(0.0, 0.05, 256, dtype=np.float32).reshape(16, 16, 1).repeat(3, axis=2)
    shown = display_transform(dark)
    assert shown.dtype == np.uint8 and shown.max() == 255
    assert np.all(np.diff(shown[..., 0].ravel().astype(int)) >= 0)  # monotonic
    assert shown[8, 0, 0] > 255 * 0.5**0.5  # gamma 1/2.2 brightens the mid-tones


def test_feature_image_restores_veiled_texture_and_suppresses_pixel_noise() -> None:
    """One texture seen near (left half) and behind a strong veil (right half: ``0.1 J + 0.6``,
    as at a few attenuation lengths), plus per-pixel noise. One tone curve leaves the veiled
    texture a few grey levels; the tile-wise equalisation more than doubles its contrast (its
    slope is bounded near the clip limit, 2, plus the clipped excess spread back) and brings it
    closer to the near half's, and the blur takes the noise's pixel-to-pixel differences down."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.uniform(0.0, 1.0, (160, 120)), (0, 0), 3.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    linear = np.concatenate([0.8 * texture, 0.1 * texture + 0.6], axis=1)[..., None].repeat(3, axis=2)

    def contrast(shown: np.ndarray) -> tuple[float, float]:
        grey = shown.astype(np.float64).mean(axis=2)
        return float(grey[:, :120].std()), float(grey[:, 120:].std())

    near, far = contrast(display_transform(linear))
    assert far < near / 4  # the veil flattens the far texture under one tone curve
    near_eq, far_eq = contrast(feature_image(display_transform(linear)))
    assert far_eq > 2 * far and far_eq / near_eq > far / near

    flat = np.full((160, 240, 3), 0.3) + rng.normal(0.0, 0.02, (160, 240, 3))
    shown, equalised = display_transform(flat), feature_image(display_transform(flat))
    step = lambda image: float(np.abs(np.diff(image.astype(np.float64).mean(axis=2), axis=1)).mean())  # noqa: E731
    # a 1 px Gaussian divides white noise's pixel differences by about 3; CLAHE gives some back
    assert step(equalised) < step(shown) / 1.5


def test_poses_register_and_match_ground_truth(sfm_run) -> None:
    scene, dataset, report, _ = sfm_run
    truth = c2w_by_name(scene / "transforms.json")
    estimate = c2w_by_name(dataset / "transforms.json")
    scene_frames = sorted(truth)
    registered = [n for n in scene_frames if n in estimate]
    rate = len(registered) / len(scene_frames)

    source = np.array([estimate[n][:3, 3] for n in registered])
    target = np.array([truth[n][:3, 3] for n in registered])
    scale, rotation, translation = umeyama(source, target)
    aligned = (scale * (rotation @ source.T)).T + translation
    errors = np.linalg.norm(aligned - target, axis=1)
    extent = float(np.linalg.norm(target.max(0) - target.min(0)))  # diagonal of the camera rig
    angles = [
        np.degrees(np.arccos(np.clip((np.trace(rotation @ estimate[n][:3, :3] @ truth[n][:3, :3].T) - 1) / 2, -1, 1)))
        for n in registered
    ]
    print(
        f"\nSfM on the water scene: registered {len(registered)}/{len(scene_frames)} ({100 * rate:.0f}%); "
        f"camera-centre error after Umeyama: max {errors.max() * 1000:.2f} mm, mean {errors.mean() * 1000:.2f} mm "
        f"= {100 * errors.max() / extent:.2f}% of the {extent:.3f} m rig extent; rotation error max {max(angles):.2f} deg"
    )
    assert rate >= 0.9
    assert errors.max() < 0.02 * extent
    assert max(angles) < 2.0


def test_unregistered_frames_are_reported_and_left_out(sfm_run) -> None:
    scene, dataset, report, _ = sfm_run
    assert report.sfm is not None
    assert set(DISTRACTORS) <= set(report.sfm.unregistered)
    assert not set(DISTRACTORS) & set(c2w_by_name(dataset / "transforms.json"))
    assert len(c2w_by_name(dataset / "transforms.json")) == len(report.sfm.registered)
    # the decoded images are still all written (only the poses are missing)
    assert sorted(p.name for p in (dataset / "images").iterdir()) == sorted(report.images)


def test_output_layout_and_inputs_untouched(sfm_run) -> None:
    scene, dataset, report, before = sfm_run
    inputs = scene / "images"
    assert {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in inputs.iterdir()} == before
    assert sorted(p.name for p in dataset.iterdir()) == [
        "depth", "images", "poses_bounds.npy", "sparse", "sparse_pc.ply", "transforms.json", "white_balance.json",
    ]  # fmt: skip
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= {p.name for p in (dataset / "sparse" / "0").iterdir()}
    poses_bounds = np.load(dataset / "poses_bounds.npy")
    assert poses_bounds.shape == (len(report.sfm.registered), 17)
    near, far = poses_bounds[:, 15], poses_bounds[:, 16]
    assert np.all(near > 0) and np.all(far > near)
    assert not list(dataset.parent.glob(".dataset.*"))  # no build folder left behind
    png = cv2.imread(str(dataset / "images" / report.images[0]), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16


def test_process_output_loads_with_seathru_data(sfm_run) -> None:
    """The process output is a valid seathru-data dataset (images/ fallback, near/far)."""
    from seathru_nerfstudio.data.seathru_dataparser import SeathruDataParserConfig

    _, dataset, report, _ = sfm_run
    outputs = SeathruDataParserConfig(data=dataset).setup().get_dataparser_outputs("train")
    names = sorted(report.sfm.registered)
    assert [p.name for p in outputs.image_filenames] == [n for i, n in enumerate(names) if i % 8 != 0]
    assert outputs.metadata["near_far"].shape == (len(outputs.image_filenames), 2)
    assert 0 < outputs.metadata["near_plane"] < outputs.metadata["far_plane"]


def test_sfm_points_become_sparse_depth_maps_that_match_the_scene(sfm_run) -> None:
    """depth/*.png (nerfstudio's depth_file_path) hold the SfM points' z-depth; up to SfM's
    global scale they match the true z-depth of the rendered scene."""
    scene, dataset, _, _ = sfm_run
    transforms = json.loads((dataset / "transforms.json").read_text())
    truth_c2w = c2w_by_name(scene / "transforms.json")
    sfm_c2w = c2w_by_name(dataset / "transforms.json")
    names = sorted(set(truth_c2w) & set(sfm_c2w))
    scale, _, _ = umeyama(np.stack([sfm_c2w[n][:3, 3] for n in names]), np.stack([truth_c2w[n][:3, 3] for n in names]))
    K = json.loads((scene / "transforms.json").read_text())
    ratios = []
    for frame in transforms["frames"]:
        sparse = cv2.imread(str(dataset / frame["depth_file_path"]), cv2.IMREAD_ANYDEPTH)
        assert sparse is not None and sparse.dtype == np.uint16
        v, u = np.nonzero(sparse)
        assert len(v) > 20, frame["depth_file_path"]
        stem = Path(frame["file_path"]).stem
        true_range = np.load(scene / "ground_truth" / "depth" / f"{stem}.npy")[v, u]
        norm = np.sqrt(((u + 0.5 - K["cx"]) / K["fl_x"]) ** 2 + ((v + 0.5 - K["cy"]) / K["fl_y"]) ** 2 + 1.0)
        hit = np.isfinite(true_range)
        ratios.append(sparse[v, u][hit] / 1000.0 * scale / (true_range[hit] / norm[hit]))
    ratios = np.concatenate(ratios)
    # pixel-rounded point positions at depth edges make a few outliers; the bulk is exact
    # the message splits a failure into a global bias (the pose-fitted scale) and per-point spread
    bias, spread = np.median(ratios) - 1.0, np.median(np.abs(ratios - np.median(ratios)))
    assert np.median(np.abs(ratios - 1.0)) < 0.02, f"median |ratio-1| {np.median(np.abs(ratios - 1.0)):.5f}: bias {bias:+.5f}, spread {spread:.5f}, {len(ratios)} points"


@pytest.mark.parametrize("mapper_scale", [0.01, 20.0])
def test_sparse_depths_do_not_wrap_whatever_the_mappers_scale(sfm_run, tmp_path, mapper_scale) -> None:
    """The mapper's scale is arbitrary. Blown up 20× (points beyond uint16's 65.535 units) or
    shrunk 100× (depths in whole millimetres), the written depth maps still hold the same
    points in one consistent gauge: each equals the unscaled run's depth times one factor."""
    import pycolmap

    from seathru_nerfstudio.data.sfm import SfmResult
    from seathru_nerfstudio.data.sfm_outputs import SPARSE_DEPTH_MAX, observed_depths, write_outputs

    _, dataset, _, _ = sfm_run
    reconstruction = pycolmap.Reconstruction(str(dataset / "sparse" / "0"))
    reconstruction.transform(pycolmap.Sim3d(mapper_scale, pycolmap.Rotation3d(), np.zeros(3)))
    if mapper_scale > 1:
        assert observed_depths(reconstruction).max() > SPARSE_DEPTH_MAX  # the case that used to wrap
    names = sorted(reconstruction.images[i].name for i in reconstruction.reg_image_ids())
    write_outputs(SfmResult(reconstruction=reconstruction, registered=names, unregistered=[]), tmp_path)
    ratios = []
    for name in names:
        before = cv2.imread(str(dataset / "depth" / name), cv2.IMREAD_ANYDEPTH).astype(np.float64)
        after = cv2.imread(str(tmp_path / "depth" / name), cv2.IMREAD_ANYDEPTH).astype(np.float64)
        both = (before > 0) & (after > 0)
        assert both.sum() > 0.95 * (before > 0).sum(), name  # points are kept, not dropped
        ratios.append(after[both] / before[both])
    ratios = np.concatenate(ratios)
    assert np.all(np.abs(ratios / np.median(ratios) - 1.0) < 1e-3), np.abs(ratios / np.median(ratios) - 1.0).max()


# ------------------------------------------------------------------ repeatability and retries
SMALL = dict(width=160, height=120, num_views=10, sfm_points_per_view=0)


def display_copies(scene: Path, folder: Path, prefix: str = "") -> Path:
    """The display copies that run_sfm reads, as seathru-process-data writes them."""
    from seathru_nerfstudio.data.linear_images import read_linear_image
    from seathru_nerfstudio.data.sfm_images import write_display_copy

    for path in sorted((scene / "images").glob("*.png")):
        write_display_copy(folder / f"{prefix}{path.name}", read_linear_image(path)[..., :3])
    return folder


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sfm_small")
    scene = generate(SynthConfig(output_dir=root / "scene", preset="water", seed=3, **SMALL))
    return display_copies(scene, root / "display")


def test_the_same_images_register_the_same_way_every_time(small_scene, tmp_path) -> None:
    """COLMAP numbers images in the order its extraction threads finish them, its matcher on
    several threads now and then keeps other matches (1 run in 85 under load), and its two-view
    RANSAC draws a new seed each run: without the fixes, the poses (and on harder captures the
    registered set) change from run to run. The mapper starts until two starts are complete and
    keeps the model that registers the most images and explains the most observations."""
    from seathru_nerfstudio.data.sfm import COMPLETE_STARTS, RETRY_BELOW_FRACTION, run_sfm
    from seathru_nerfstudio.data.sfm_models import complete_starts, num_observations

    runs = []
    for k in range(3):
        result = run_sfm(small_scene, tmp_path / f"work_{k}", camera_model="PINHOLE")
        reconstruction = result.reconstruction
        poses = {reconstruction.images[i].name: reconstruction.images[i].cam_from_world().matrix() for i in reconstruction.reg_image_ids()}
        runs.append((result.registered, poses, reconstruction.num_points3D()))
        # from each camera start, a complete model is checked against another complete start, and the mapper stops there
        assert result.cameras[0] == "uncalibrated camera" and len(set(result.cameras)) == 3
        for camera in set(result.cameras):
            counts = [n for n, c in zip(result.attempts, result.cameras) if c == camera]
            assert complete_starts(counts, len(result.registered), RETRY_BELOW_FRACTION) == COMPLETE_STARTS
            assert complete_starts(counts[:-1], len(result.registered), RETRY_BELOW_FRACTION) == COMPLETE_STARTS - 1
        assert set(result.descriptors) == {"SIFT"}  # registered fully: no second descriptor pass
        ranks = list(zip(result.attempts, result.observations))
        assert ranks[result.kept] == max(ranks) == (len(result.registered), num_observations(reconstruction))
        assert result.disagreement_deg[result.kept] == pytest.approx(0.0, abs=1e-6)
    names = sorted(p.name for p in small_scene.iterdir())
    for registered, poses, num_points in runs:
        assert registered == names  # registers fully ...
        assert num_points == runs[0][2]
        for name in names:  # ... and identically, to the last bit
            assert np.array_equal(poses[name], runs[0][1][name]), name


def test_a_small_registration_is_retried_then_refused_below_the_users_minimum(small_scene, tmp_path) -> None:
    """Two unrelated scenes in one folder: the best model holds at most one of them, so the mapper
    tries its other settings from each camera start with each kind of descriptor in turn, and a minimum above that share
    fails naming the folder."""
    import shutil

    from seathru_nerfstudio.data.sfm import DESCRIPTOR_PASSES, MAPPER_ATTEMPTS, RETRY_BELOW_FRACTION, SfmError, camera_starts, run_sfm

    other = generate(SynthConfig(output_dir=tmp_path / "other", preset="fog", seed=11, **SMALL))
    mixed = display_copies(other, tmp_path / "mixed", prefix="other_")
    for path in small_scene.iterdir():
        shutil.copy(path, mixed / path.name)
    total = len(list(mixed.iterdir()))
    result = run_sfm(mixed, tmp_path / "work", camera_model="PINHOLE", min_registered_fraction=0.0, source="capture/")
    assert len(result.registered) <= total - SMALL["num_views"] < RETRY_BELOW_FRACTION * total
    labels = [label for label, _ in DESCRIPTOR_PASSES]
    starts = [label for label, _ in camera_starts("PINHOLE", None, mixed / sorted(p.name for p in mixed.iterdir())[0])]
    # every setting, from every camera start, with every descriptor
    assert result.descriptors == [label for label in labels for _ in starts for _ in MAPPER_ATTEMPTS]
    assert result.cameras == [start for _ in labels for start in starts for _ in MAPPER_ATTEMPTS]
    assert len(result.attempts) == len(result.descriptors) == len(result.observations)
    assert len(result.registered) == max(result.attempts)  # and the best model kept
    with pytest.raises(SfmError, match=r"registered only \d+ of the 20 images of capture/ .*--min-registered-fraction 0.6"):
        # one camera start (a known focal length) is enough to reach the refusal, and halves the mapper's runs
        run_sfm(mixed, tmp_path / "work_2", camera_model="PINHOLE", min_registered_fraction=0.6, source="capture/", focal_length_px=100.0)


def test_every_data_path_gives_the_method_the_same_sfm(sfm_run, tmp_path, monkeypatch) -> None:
    """Without depth maps, the published layout (seathru-data: sparse/0) and ns-process-data's
    (nerfstudio-data: colmap/sparse/0) get sparse depths made from the COLMAP model's tracks, which
    agree with seathru-process-data's depth/ maps wherever both hold a point, and the method gets
    its SfM from them (bounds, range spread, observation table). The dataset is never written to."""
    import shutil

    from seathru_nerfstudio.data.nerfstudio_data import SeathruNerfstudioDataParserConfig, read_sparse_depths
    from seathru_nerfstudio.data.seathru_dataparser import SeathruDataParserConfig
    from seathru_nerfstudio.metadata_keys import RANGE_SPREAD_KEY, SFM_OBSERVATIONS_KEY

    monkeypatch.setenv("SEATHRU_CACHE", str(tmp_path / "cache"))
    _, dataset, _, _ = sfm_run
    ours = SeathruNerfstudioDataParserConfig(data=dataset).setup().get_dataparser_outputs("train")
    published = tmp_path / "published"  # images/ and sparse/0 only, as the SeaThru-NeRF release
    shutil.copytree(dataset / "images", published / "images")
    shutil.copytree(dataset / "sparse", published / "sparse")
    shutil.copy(dataset / "poses_bounds.npy", published)
    ns_layout = tmp_path / "ns"  # ns-process-data: transforms.json without depths, colmap/sparse/0
    shutil.copytree(dataset / "images", ns_layout / "images")
    shutil.copytree(dataset / "sparse", ns_layout / "colmap" / "sparse")
    transforms = json.loads((dataset / "transforms.json").read_text())
    for frame in transforms["frames"]:
        frame.pop("depth_file_path")
    (ns_layout / "transforms.json").write_text(json.dumps(transforms))
    before = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(tmp_path.rglob("*")) if p.is_file()}
    theirs = {
        "published": SeathruDataParserConfig(data=published).setup().get_dataparser_outputs("train"),
        "ns": SeathruNerfstudioDataParserConfig(data=ns_layout).setup().get_dataparser_outputs("train"),
    }
    after = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(tmp_path.rglob("*")) if p.is_file() and "cache" not in p.parts}
    assert after == {p: h for p, h in before.items() if "cache" not in p.parts}
    ours_by_name = dict(zip((p.name for p in ours.image_filenames), ours.metadata["depth_filenames"]))
    for name, outputs in theirs.items():
        assert outputs.metadata[SFM_OBSERVATIONS_KEY].num_observations > 0 and RANGE_SPREAD_KEY in outputs.metadata, name
        unit = float(outputs.metadata["depth_unit_scale_factor"])
        heights, widths = outputs.cameras.height, outputs.cameras.width
        maps = read_sparse_depths(outputs.metadata["depth_filenames"], heights, widths)
        for image, made in zip(outputs.image_filenames, maps):
            if image.name not in ours_by_name:
                continue
            (written,) = read_sparse_depths([ours_by_name[image.name]], heights[:1], widths[:1])
            both = (made > 0) & (written > 0)
            assert both.sum() > 10, (name, image.name)
            np.testing.assert_allclose(made[both] * unit, written[both] * 1e-3, rtol=2e-3, atol=2e-3)


def test_a_dataset_with_no_sfm_at_all_says_in_one_line_what_is_lost(tmp_path, capsys) -> None:
    from types import SimpleNamespace

    from seathru_nerfstudio.data.nerfstudio_data import depths_from_colmap

    outputs = SimpleNamespace(image_filenames=[tmp_path / "a.png"], metadata={})
    depths_from_colmap(outputs, tmp_path)
    message = " ".join(capsys.readouterr().out.split())
    assert str(tmp_path) in message and "no COLMAP model" in message and "medium fit" in message
    assert "depth_filenames" not in outputs.metadata


@pytest.mark.parametrize("model, count", [("SIMPLE_PINHOLE", 3), ("PINHOLE", 4), ("SIMPLE_RADIAL", 4), ("OPENCV", 8)])
def test_the_camera_starts_at_a_known_or_guessed_focal_length_marked_as_a_prior(small_scene, tmp_path, model, count) -> None:
    """``--focal-length-px``: the shared camera enters the database with that focal length, the principal
    point at the image centre and no distortion, marked as a prior, and is the only camera start; without
    it, the first start is COLMAP's unmarked guess, the second the same at 1.2 × the long side marked as a prior, and
    the third at 0.5 × the long side (a 90° field of view), marked too."""
    import pycolmap

    from seathru_nerfstudio.data.sfm import (
        GUESSED_FOCAL_PER_LONG_SIDE,
        WIDE_FOCAL_PER_LONG_SIDE,
        SfmError,
        _extract_and_match,
        camera_starts,
        prior_camera_params,
    )

    names = sorted(p.name for p in small_scene.glob("*.png"))[:3]
    height, width = cv2.imread(str(small_scene / names[0])).shape[:2]
    for focal, expect_focal in ((123.5, 123.5), (None, GUESSED_FOCAL_PER_LONG_SIDE * max(width, height))):
        params = prior_camera_params(model, focal, small_scene / names[0])
        database = tmp_path / f"{focal}.db"
        _extract_and_match(database, small_scene, names, model, params, "exhaustive", {}, "SIFT", False)
        db = pycolmap.Database.open(str(database))
        (camera,) = db.read_all_cameras()
        db.close()
        assert camera.has_prior_focal_length and len(camera.params) == count
        assert (camera.focal_length_x, camera.focal_length_y) == pytest.approx([expect_focal] * 2)
        assert (camera.principal_point_x, camera.principal_point_y) == pytest.approx((width / 2, height / 2))
        assert not np.any(np.asarray(camera.params)[camera.extra_params_idxs()])
    for bad in (0.0, -5.0, float("nan"), float("inf")):
        with pytest.raises(SfmError, match="--focal-length-px"):
            prior_camera_params(model, bad, small_scene / names[0])
    guess, wide = (ratio * max(width, height) for ratio in (GUESSED_FOCAL_PER_LONG_SIDE, WIDE_FOCAL_PER_LONG_SIDE))
    assert wide < guess
    assert camera_starts(model, None, small_scene / names[0]) == [
        ("uncalibrated camera", ""),
        (f"camera from {guess:.0f} px", prior_camera_params(model, None, small_scene / names[0])),
        (f"camera from {wide:.0f} px", prior_camera_params(model, wide, small_scene / names[0])),
    ]
    assert camera_starts(model, 123.5, small_scene / names[0]) == [("camera from 124 px", prior_camera_params(model, 123.5, small_scene / names[0]))]


def test_a_further_camera_start_reuses_the_matches_and_verifies_them_as_a_fresh_extraction_would(small_scene, tmp_path) -> None:
    """The marked camera start copies the first start's features and matches and runs the two-view verification
    again: its database holds the same camera, the same verified pairs and the same inlier matches as extracting
    and matching anew under that camera, and differs from the first start's, whose camera is not marked."""
    import pycolmap

    from seathru_nerfstudio.data.sfm import _extract_and_match, _verify_again, camera_starts

    names = sorted(p.name for p in small_scene.glob("*.png"))[:6]
    (_, unmarked), (_, marked), _ = camera_starts("SIMPLE_PINHOLE", None, small_scene / names[0])
    _extract_and_match(tmp_path / "first.db", small_scene, names, "SIMPLE_PINHOLE", unmarked, "exhaustive", {}, "SIFT", False)
    _extract_and_match(tmp_path / "fresh.db", small_scene, names, "SIMPLE_PINHOLE", marked, "exhaustive", {}, "SIFT", False)
    _verify_again(tmp_path / "first.db", tmp_path / "reused.db", marked, False)

    def contents(name: str):
        db = pycolmap.Database.open(str(tmp_path / name))
        (camera,) = db.read_all_cameras()
        pair_ids, geometries = db.read_two_view_geometries()
        db.close()
        verified = {i: (int(g.config), np.asarray(g.inlier_matches).tolist()) for i, g in zip(pair_ids, geometries)}
        return (camera.has_prior_focal_length, list(camera.params)), verified

    first, fresh, reused = contents("first.db"), contents("fresh.db"), contents("reused.db")
    assert reused == fresh
    assert first[0][0] is False and reused[0][0] is True
    assert any(first[1].get(i, (None,))[0] != config for i, (config, _) in reused[1].items())  # the camera changed the verification
