"""Tests for the synthetic scene generator (seathru_nerfstudio.data.synthetic / seathru-synth)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from seathru_nerfstudio.data.io import OutputFolderError
from seathru_nerfstudio.data.synthetic import GROUND_Y, PRESETS, WALL_Z, SynthConfig, SynthError, apply_medium, generate

W, H, N = 48, 36, 7
Q = 1.0 / 65535.0  # one 16-bit quantisation step


def _read_rgb16(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    assert img.dtype == np.uint16 and img.ndim == 3 and img.shape[2] == 3, (path, img.dtype, img.shape)
    return img[..., ::-1]  # cv2 gives BGR


def _load(out: Path, i: int):
    stem = f"frame_{i:05d}"
    I = _read_rgb16(out / "images" / f"{stem}.png").astype(np.float64) / 65535.0
    J = _read_rgb16(out / "ground_truth" / "clean" / f"{stem}.png").astype(np.float64) / 65535.0
    z = np.load(out / "ground_truth" / "depth" / f"{stem}.npy")
    return I, J, z


def _files(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def water(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "water"
    assert generate(SynthConfig(output_dir=out, width=W, height=H, num_views=N)) == out
    return out


@pytest.fixture(scope="module")
def water_exact(tmp_path_factory) -> Path:
    """No supersampling: every pixel follows the formation model exactly."""
    out = tmp_path_factory.mktemp("synth") / "water_ss1"
    generate(SynthConfig(output_dir=out, width=W, height=H, num_views=N, supersample=1, seed=3))
    return out


def test_layout_shapes_and_dtypes(water: Path):
    assert sorted(p.name for p in water.iterdir()) == ["depth", "ground_truth", "images", "transforms.json"]
    for i in range(N):
        I, J, z = _load(water, i)
        assert I.shape == J.shape == (H, W, 3)
        assert z.shape == (H, W) and z.dtype == np.float32
    assert len(list((water / "images").glob("*.png"))) == N
    assert not list(water.parent.glob(".water.*")), "temporary folders left behind"
    med = json.loads((water / "ground_truth" / "medium.json").read_text())
    assert med["preset"] == "water" and med["units"] == "1/m" and med["world_units"] == "m"
    assert med["color_space"] == "linear"
    for key in ("beta_D", "beta_B", "B_inf"):
        assert med[key] == PRESETS["water"][key]
    assert (med["width"], med["height"], med["seed"]) == (W, H, 0)


def test_same_seed_identical_different_seed_differs(water: Path, tmp_path: Path):
    again = generate(SynthConfig(output_dir=tmp_path / "again", width=W, height=H, num_views=N))
    a, b = _files(water), _files(again)
    assert a.keys() == b.keys()
    assert all(a[k] == b[k] for k in a), [k for k in a if a[k] != b[k]]
    other = _files(generate(SynthConfig(output_dir=tmp_path / "other", width=W, height=H, num_views=N, seed=1)))
    assert other.keys() == a.keys()
    assert all(other[k] != a[k] for k in a if k.startswith("images/"))
    assert other["transforms.json"] != a["transforms.json"]


def test_value_ranges(water: Path):
    zs, Js = [], []
    for i in range(N):
        I, J, z = _load(water, i)
        zs.append(z)
        Js.append(J[np.isfinite(z)])
    z = np.stack(zs)
    finite = z[np.isfinite(z)]
    assert 0.6 < finite.min() < 0.9, finite.min()
    assert 2.0 < finite.max() < 3.0, finite.max()
    J = np.concatenate(Js)
    assert np.percentile(J, 1) > 0.03 and J.max() < 0.96
    assert J.std() > 0.08  # textured, not flat


def test_formation_model_exact(water_exact: Path):
    med = json.loads((water_exact / "ground_truth" / "medium.json").read_text())
    bD, bB, Binf = (np.array(med[k]) for k in ("beta_D", "beta_B", "B_inf"))
    for i in range(N):
        I, J, z = _load(water_exact, i)
        finite = np.isfinite(z)
        zf = np.where(finite, z, 0.0)[..., None].astype(np.float64)
        rec = np.where(finite[..., None], J * np.exp(-bD * zf) + Binf * (1.0 - np.exp(-bB * zf)), Binf)
        err = np.abs(rec - I)
        # J and I are each rounded to 16 bits: |error| <= 0.5 Q (J, attenuated) + 0.5 Q (I)
        assert err.max() <= 1.01 * Q, (i, err.max() / Q)
        # ... and the medium matters: ignoring it would be far off
        assert np.abs(J - I)[finite].mean() > 0.05
    # the helper agrees with the written formula
    I, J, z = _load(water_exact, 0)
    assert np.abs(apply_medium(J, z.astype(np.float64), bD, bB, Binf) - I).max() <= 1.01 * Q


def test_formation_model_supersampled_is_close(water: Path):
    """With anti-aliasing the model holds per sub-sample, so per pixel only approximately."""
    med = json.loads((water / "ground_truth" / "medium.json").read_text())
    bD, bB, Binf = (np.array(med[k]) for k in ("beta_D", "beta_B", "B_inf"))
    errs = []
    for i in range(N):
        I, J, z = _load(water, i)
        errs.append(np.abs(apply_medium(J, z.astype(np.float64), bD, bB, Binf) - I).ravel())
    errs = np.concatenate(errs)
    assert np.median(errs) < 2 * Q
    assert np.percentile(errs, 90) < 0.01


def test_open_water_is_B_inf(water: Path):
    Binf = np.array(PRESETS["water"]["B_inf"])
    fractions = []
    for i in range(N):
        I, J, z = _load(water, i)
        ow = ~np.isfinite(z)
        fractions.append(ow.mean())
        assert ow.any(), f"view {i} shows no open water"
        assert np.isinf(z[ow]).all() and (z[~ow] > 0).all()
        assert np.abs(I[ow] - Binf).max() <= 0.5 * Q + 1e-12
        assert (J[ow] == 0).all()
        # open water is at the top of the frame (above the wall), not at the bottom
        assert ow[0].mean() > 0.3 and ow[-1].mean() == 0.0
    assert 0.05 < np.mean(fractions) < 0.5


def test_none_preset_equals_clean(tmp_path: Path):
    out = generate(SynthConfig(output_dir=tmp_path / "clear", preset="none", width=W, height=H, num_views=3))
    for i in range(3):
        stem = f"frame_{i:05d}.png"
        I = cv2.imread(str(out / "images" / stem), cv2.IMREAD_UNCHANGED)
        J = cv2.imread(str(out / "ground_truth" / "clean" / stem), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(I, J)
        assert I.max() > 30000  # not an all-black image
    med = json.loads((out / "ground_truth" / "medium.json").read_text())
    assert med["beta_D"] == [0.0] * 3 and med["B_inf"] == [0.0] * 3


def test_fog_is_grey_and_veils(tmp_path: Path):
    out = generate(SynthConfig(output_dir=tmp_path / "fog", preset="fog", width=W, height=H, num_views=2))
    I, J, z = _load(out, 0)
    ow = ~np.isfinite(z)
    assert np.allclose(I[ow], 0.6, atol=Q)
    far = np.isfinite(z) & (z > 1.5)
    assert far.any()
    # far objects are mostly veiled: closer to the veiling light than the clean image is
    assert np.abs(I[far] - 0.6).mean() < 0.5 * np.abs(J[far] - 0.6).mean()


def test_transforms_poses_and_splits(water: Path):
    meta = json.loads((water / "transforms.json").read_text())
    assert meta["camera_model"] in ("OPENCV", "PINHOLE")
    assert (meta["w"], meta["h"]) == (W, H)
    assert meta["fl_x"] == pytest.approx(0.5 * W / np.tan(np.radians(30.0)))
    assert meta["cx"] == W / 2 and meta["cy"] == H / 2
    names = [f["file_path"] for f in meta["frames"]]
    assert names == [f"images/frame_{i:05d}.png" for i in range(N)]
    for f in meta["frames"]:
        assert (water / f["file_path"]).is_file()
        stem = Path(f["file_path"]).stem  # each frame declares its ground truth
        assert f["gt_clean_file_path"] == f"ground_truth/clean/{stem}.png" and (water / f["gt_clean_file_path"]).is_file()
        assert f["gt_depth_file_path"] == f"ground_truth/depth/{stem}.npy" and (water / f["gt_depth_file_path"]).is_file()
        T = np.array(f["transform_matrix"])
        assert T.shape == (4, 4)
        assert np.allclose(T[3], [0, 0, 0, 1])
        R = T[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
        assert R[2, 2] > 0.9  # camera's -z axis looks towards world -z (forward-facing rig)
        assert R[1, 1] > 0.9  # camera +y is (roughly) world up
    centres = np.array([np.array(f["transform_matrix"])[:3, 3] for f in meta["frames"]])
    extent = centres.max(0) - centres.min(0)
    assert 0.2 < extent[0] < 0.7 and 0.1 < extent[1] < 0.5 and extent[2] < 0.1
    train, val, test = (meta[f"{s}_filenames"] for s in ("train", "val", "test"))
    held = [names[i] for i in range(0, N, 5)]
    assert val == held and test == held
    assert not set(train) & set(val)
    assert sorted(set(train) | set(val) | set(test)) == sorted(names)


def test_depth_is_range_consistent_across_views(water_exact: Path):
    """Back-project view 0 with its range (OpenGL camera, pixel centres at +0.5) and re-project into
    view 1: visible points must land where view 1 sees the same range. Checks pose convention,
    intrinsics and that depth is Euclidean range (not z-depth)."""
    meta = json.loads((water_exact / "transforms.json").read_text())
    fx, fy, cx, cy = meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]
    T0, T1 = (np.array(meta["frames"][k]["transform_matrix"]) for k in (0, 1))
    z0 = np.load(water_exact / "ground_truth" / "depth" / "frame_00000.npy").astype(np.float64)
    z1 = np.load(water_exact / "ground_truth" / "depth" / "frame_00001.npy").astype(np.float64)
    v, u = np.nonzero(np.isfinite(z0))
    dc = np.stack([(u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -np.ones(len(u))], 1)
    dc /= np.linalg.norm(dc, axis=1, keepdims=True)
    X = T0[:3, 3] + (dc * z0[v, u][:, None]) @ T0[:3, :3].T
    Xc = (X - T1[:3, 3]) @ T1[:3, :3]  # world -> camera 1
    u1 = fx * Xc[:, 0] / -Xc[:, 2] + cx - 0.5
    v1 = -fy * Xc[:, 1] / -Xc[:, 2] + cy - 0.5
    iu, iv = np.round(u1).astype(int), np.round(v1).astype(int)
    inside = (iu >= 0) & (iu < W) & (iv >= 0) & (iv < H)
    r1 = np.linalg.norm(Xc, axis=1)[inside]
    seen = z1[iv[inside], iu[inside]]
    agree = np.abs(seen - r1) < 0.03 * r1
    assert inside.mean() > 0.5 and agree.mean() > 0.8, (inside.mean(), agree.mean())
    # Absolute check: back-projected points land on the known back wall / ground planes (a z-depth
    # stored as if it were range would pull off-centre points in front of them).
    on_wall = np.abs(X[:, 2] - WALL_Z) < 2e-3
    on_ground = np.abs(X[:, 1] - GROUND_Y) < 2e-3
    assert (on_wall | on_ground).mean() > 0.4, (on_wall.mean(), on_ground.mean())
    assert (X[:, 2] > WALL_Z - 2e-3).all() and (X[:, 1] > GROUND_Y - 2e-3).all()
    off_centre = np.abs(u + 0.5 - cx) > W / 4
    assert (on_wall & off_centre).sum() > 20


def test_nerfstudio_parses_it(water: Path):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    n_held = len(range(0, N, 5))
    parser = NerfstudioDataParserConfig(data=water).setup()
    train = parser.get_dataparser_outputs("train")
    assert len(train.image_filenames) == N - n_held
    assert all(Path(p).name != "frame_00000.png" for p in train.image_filenames)
    assert int(train.cameras.width[0]) == W and int(train.cameras.height[0]) == H
    val = NerfstudioDataParserConfig(data=water).setup().get_dataparser_outputs("val")
    assert len(val.image_filenames) == n_held


def test_refuses_non_empty_output_dir(tmp_path: Path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(OutputFolderError, match="--overwrite") as exc:
        generate(SynthConfig(output_dir=out, width=16, height=12, num_views=2))
    assert str(out) in str(exc.value)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy"], "temporary folder left behind"
    # an existing empty folder is fine
    empty = tmp_path / "empty"
    empty.mkdir()
    generate(SynthConfig(output_dir=empty, width=16, height=12, num_views=2))
    assert (empty / "transforms.json").is_file()
    # --overwrite replaces the old contents
    generate(SynthConfig(output_dir=out, width=16, height=12, num_views=2, overwrite=True))
    assert not (out / "keep.txt").exists() and (out / "transforms.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy", "empty"]


def _cli() -> str:
    exe = Path(sys.executable).parent / "seathru-synth"
    found = str(exe) if exe.exists() else shutil.which("seathru-synth")
    assert found is not None, "seathru-synth is not installed (pip install -e .)"
    return found


def test_cli(tmp_path: Path):
    exe = _cli()
    out = tmp_path / "cli"
    args = [exe, "--output-dir", str(out), "--num-views", "4", "--width", "32", "--height", "24"]
    res = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    meta = json.loads((out / "transforms.json").read_text())
    assert len(meta["frames"]) == 4 and meta["w"] == 32 and meta["h"] == 24
    assert _read_rgb16(out / "images" / "frame_00003.png").shape == (24, 32, 3)
    # same call again: folder is now non-empty -> refused, naming the folder
    res = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert res.returncode == 1 and str(out) in (res.stdout + res.stderr).replace("\n", "")
    # bad calls
    for bad in (
        [exe],  # missing --output-dir
        [exe, "--output-dir", str(tmp_path / "x"), "--preset", "lava"],
        [exe, "--output-dir", str(tmp_path / "y"), "--num-views", "1"],
    ):
        res = subprocess.run(bad, capture_output=True, text=True, timeout=120)
        assert res.returncode != 0, bad
        assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_sfm_depth_is_sparse_true_z_depth_on_textured_object_pixels(water_exact: Path):
    """depth/*.png hold z-depth in mm at a few textured pixels, 0 elsewhere, never in open water."""
    frames = json.loads((water_exact / "transforms.json").read_text())["frames"]
    K = json.loads((water_exact / "transforms.json").read_text())
    for i, frame in enumerate(frames):
        sparse = cv2.imread(str(water_exact / frame["depth_file_path"]), cv2.IMREAD_ANYDEPTH)
        _, _, z = _load(water_exact, i)
        known = sparse > 0
        assert 0 < known.sum() <= SynthConfig(output_dir=Path(".")).sfm_points_per_view
        assert np.isfinite(z[known]).all(), "an SfM point in open water"
        v, u = np.nonzero(known)
        norm = np.sqrt(((u + 0.5 - K["cx"]) / K["fl_x"]) ** 2 + ((v + 0.5 - K["cy"]) / K["fl_y"]) ** 2 + 1.0)
        np.testing.assert_allclose(sparse[known] / 1000.0, z[known] / norm, atol=6e-4)


def test_turbid_preset_is_deeper_greener_and_follows_the_model(tmp_path: Path):
    out = generate(SynthConfig(output_dir=tmp_path / "turbid", preset="turbid", width=W, height=H, num_views=2, supersample=1))
    med = json.loads((out / "ground_truth" / "medium.json").read_text())
    assert med["beta_D"] == PRESETS["turbid"]["beta_D"]
    I, J, z = _load(out, 0)
    hit = np.isfinite(z)
    assert z[hit].min() < 1.6 and z[hit].max() > 6.0, (z[hit].min(), z[hit].max())
    assert np.argmax(PRESETS["turbid"]["B_inf"]) == 1  # green water, unlike water's blue
    expected = apply_medium(J, z, med["beta_D"], med["beta_B"], med["B_inf"])
    np.testing.assert_allclose(I, expected, atol=2e-5)


def test_bad_options_are_refused_before_anything_is_written(tmp_path: Path):
    for bad in ({"num_views": 1}, {"width": 4}, {"supersample": 0}, {"rig_depth": -0.5}):
        with pytest.raises(SynthError):
            generate(SynthConfig(output_dir=tmp_path / "x", **bad))
    assert not any(tmp_path.iterdir())


def test_rig_depth_steps_cameras_back_along_the_axis_and_keeps_them_aimed():
    """``rig_depth`` moves only the centres' z (over [0, rig_depth], jitter aside), draws no extra
    random numbers, and every camera still looks at the same target: the range of one scene point
    then differs between views by a large fraction of ``rig_depth``."""
    from seathru_nerfstudio.data.synthetic.cameras import LOOK_AT, make_poses
    from seathru_nerfstudio.data.synthetic.scene import Geometry

    flat = make_poses(np.random.default_rng(3), 20, Geometry())
    deep = make_poses(np.random.default_rng(3), 20, Geometry(rig_depth=1.0))
    np.testing.assert_allclose(deep[:, :2, 3], flat[:, :2, 3])
    back = deep[:, 2, 3] - flat[:, 2, 3]
    assert back.min() >= 0.0 and back.max() <= 1.0 and back.max() - back.min() > 0.9
    for pose in deep:  # the viewing axis (-z) passes within the target jitter of LOOK_AT
        to_target = LOOK_AT - pose[:3, 3]
        off_axis = to_target - (to_target @ -pose[:3, 2]) * -pose[:3, 2]
        assert np.linalg.norm(off_axis) < 0.11
    ranges = lambda poses: np.linalg.norm(poses[:, :3, 3] - LOOK_AT, axis=1)  # noqa: E731
    assert ranges(deep).std() > 5 * ranges(flat).std()


def test_scaled_wall_is_the_same_wall_farther_away():
    """The turbid preset scales the scene about the rig: the wall's tabulated top edge (built
    when the wall is) must scale with it."""
    from seathru_nerfstudio.data.synthetic.scene import Wall, build_scene

    wall = build_scene(np.random.default_rng(0)).prims[0]
    assert isinstance(wall, Wall)
    x = wall.top_x[::2]  # knots of the wall whose 3.5x are knots of the scaled wall
    far = wall.scaled(3.5)
    np.testing.assert_allclose(far.top(3.5 * x), 3.5 * wall.top(x), rtol=0, atol=1e-9)
    assert np.ptp(wall.top(x)) > 0.05  # an irregular edge, not a straight one
