"""16-bit linear images reach the model at full precision; nerfstudio's own loader does not."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

from seathru_nerfstudio.data.linear_images import ImageReadError, LinearImageDataset, read_linear_image


def write_png16(path, rgb: np.ndarray) -> None:
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def low_byte_ramp(height: int = 6, width: int = 8) -> np.ndarray:
    """Dark linear values that differ only in their low byte (all < 256/65535)."""
    values = np.arange(height * width * 3, dtype=np.uint16).reshape(height, width, 3) + 7
    return values


def test_read_linear_image_keeps_16_bits_and_rgb_order(tmp_path):
    ramp = low_byte_ramp()
    write_png16(tmp_path / "a.png", ramp)
    image = read_linear_image(tmp_path / "a.png")
    assert image.dtype == np.float32 and image.shape == ramp.shape
    np.testing.assert_allclose(image * 65535.0, ramp, atol=1e-2)
    assert len(np.unique(image)) == ramp.size


def test_read_linear_image_8_bit_grey_and_errors(tmp_path):
    grey = (np.arange(48, dtype=np.uint8).reshape(6, 8) * 5).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "g.png"), grey)
    image = read_linear_image(tmp_path / "g.png")
    assert image.shape == (6, 8, 3)
    np.testing.assert_allclose(image[..., 1], grey / 255.0, atol=1e-7)
    with pytest.raises(ImageReadError, match="no such image"):
        read_linear_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"not a png at all")
    with pytest.raises(ImageReadError, match="bad.png"):
        read_linear_image(tmp_path / "bad.png")


@pytest.fixture()
def tiny_dataset(tmp_path):
    ramp = low_byte_ramp()
    (tmp_path / "images").mkdir()
    frames = []
    for i in range(3):
        write_png16(tmp_path / "images" / f"f{i}.png", ramp + i)
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": pose.tolist()})
    meta = {"fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    outputs = NerfstudioDataParserConfig(data=tmp_path, train_split_fraction=1.0).setup().get_dataparser_outputs("train")
    return outputs, ramp


def test_nerfstudio_loader_loses_the_low_bits_ours_keeps_them(tiny_dataset):
    outputs, ramp = tiny_dataset
    theirs = InputDataset(outputs)[0]["image"]
    ours = LinearImageDataset(outputs)[0]["image"]
    assert ours.dtype == torch.float32 and ours.shape == theirs.shape
    # nerfstudio: every pixel of this dark 16-bit ramp collapses to one or two 8-bit levels
    assert len(torch.unique(theirs)) < 5
    assert len(torch.unique(ours)) == ramp.size
    np.testing.assert_allclose(ours.numpy() * 65535.0, ramp, atol=1e-2)
    assert not {"gt_clean", "gt_depth", "depth_image"} & set(LinearImageDataset(outputs)[0])  # none declared


def test_sparse_depth_images_reach_the_batch_in_scene_units(tmp_path):
    """seathru-synth's SfM-like depth/ (nerfstudio's depth_file_path, mm) arrives as
    ``depth_image`` in scene units, and the parser tells the model its scale."""
    import cv2

    from seathru_nerfstudio.data.nerfstudio_data import EXTENT_KEY, SCALE_KEY, SeathruNerfstudioDataParserConfig
    from seathru_nerfstudio.data.synthetic import SynthConfig, generate
    from seathru_nerfstudio.metadata_keys import VERTICAL_KEY

    scene = generate(SynthConfig(output_dir=tmp_path / "s", width=24, height=16, num_views=3, sfm_points_per_view=20))
    outputs = SeathruNerfstudioDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    scale = float(outputs.dataparser_scale)
    assert outputs.metadata[SCALE_KEY] == scale
    vertical = torch.tensor(outputs.metadata[VERTICAL_KEY], dtype=torch.float64)  # the cameras' up, made unit
    assert float(vertical.norm()) == pytest.approx(1.0) and float(vertical @ outputs.cameras.camera_to_worlds[:, :3, 1].double().mean(0)) > 0
    item = LinearImageDataset(outputs)[0]
    stored = cv2.imread(str(outputs.metadata["depth_filenames"][0]), cv2.IMREAD_ANYDEPTH)
    assert item["depth_image"].shape == (16, 24, 1)
    known = stored > 0
    assert known.sum() == 20
    np.testing.assert_allclose(item["depth_image"][..., 0].numpy()[known], stored[known] * 1e-3 * scale, rtol=1e-6)
    assert (item["depth_image"][..., 0].numpy()[~known] == 0).all()
    # the nearest SfM depths bound where objects can be: about the nearest true range
    true_range = min(float(np.load(p).min()) for p in (scene / "ground_truth" / "depth").glob("*.npy"))
    near_m = outputs.metadata["near_plane"] / scale
    assert 0.8 * true_range < near_m < 1.5 * true_range, (near_m, true_range)
    # the contraction's extent: every SfM point (back-projected, scene units) lies inside it
    c2w = outputs.cameras.camera_to_worlds[0].double()
    v, u = np.nonzero(known)
    z = stored[known] * 1e-3 * scale
    fx, fy, cx, cy = (float(getattr(outputs.cameras, k)[0]) for k in ("fx", "fy", "cx", "cy"))
    local = np.stack([(u + 0.5 - cx) / fx * z, -(v + 0.5 - cy) / fy * z, -z], axis=-1)
    points = local @ c2w[:, :3].numpy().T + c2w[:, 3].numpy()
    assert np.abs(points).max() <= outputs.metadata[EXTENT_KEY] + 1e-6


def _synth_scene(root, name="s"):
    from seathru_nerfstudio.data.synthetic import SynthConfig, generate

    return generate(SynthConfig(output_dir=root / name, width=24, height=16, num_views=3, sfm_points_per_view=20))


def _parse(scene, split="train"):
    from seathru_nerfstudio.data.nerfstudio_data import SeathruNerfstudioDataParserConfig

    return SeathruNerfstudioDataParserConfig(data=scene).setup().get_dataparser_outputs(split)


def _edit_frames(scene, edit):
    meta = json.loads((scene / "transforms.json").read_text())
    for index, frame in enumerate(meta["frames"]):
        edit(index, frame)
    (scene / "transforms.json").write_text(json.dumps(meta))


def test_ground_truth_comes_from_the_frames_not_from_the_image_paths(tmp_path):
    """The dataset loads the files each frame declares, wherever they are."""
    scene = _synth_scene(tmp_path)
    (scene / "ground_truth").rename(scene / "truth")  # where no rule based on image paths looks

    def move(index, frame):
        for field in ("gt_clean_file_path", "gt_depth_file_path"):
            frame[field] = frame[field].replace("ground_truth/", "truth/")

    _edit_frames(scene, move)
    outputs = _parse(scene)
    names = [p.name for p in outputs.image_filenames]
    assert names == ["frame_00001.png", "frame_00002.png"]  # frame 0 is held out
    assert [p.name for p in outputs.metadata["gt_clean_filenames"]] == names
    assert [p.name for p in outputs.metadata["gt_depth_filenames"]] == ["frame_00001.npy", "frame_00002.npy"]
    item = LinearImageDataset(outputs)[1]
    clean = read_linear_image(scene / "truth" / "clean" / "frame_00002.png")
    np.testing.assert_array_equal(item["gt_clean"].numpy(), clean)
    depth = np.load(scene / "truth" / "depth" / "frame_00002.npy")
    np.testing.assert_array_equal(item["gt_depth"][..., 0].numpy(), depth * np.float32(outputs.dataparser_scale))
    assert torch.isinf(item["gt_depth"]).any() and torch.isfinite(item["gt_depth"]).any()  # open water and objects


def test_older_synthetic_scenes_without_declared_ground_truth_still_load(tmp_path):
    scene = _synth_scene(tmp_path)
    _edit_frames(scene, lambda index, frame: [frame.pop(f) for f in ("gt_clean_file_path", "gt_depth_file_path")])
    with pytest.warns(UserWarning, match="declares no ground truth"):
        outputs = _parse(scene)
    item = LinearImageDataset(outputs)[0]
    np.testing.assert_array_equal(item["gt_clean"].numpy(), read_linear_image(scene / "ground_truth" / "clean" / "frame_00001.png"))
    assert item["gt_depth"].shape == (16, 24, 1)
    (scene / "ground_truth").rename(scene / "elsewhere")  # a dataset without ground truth has none
    item = LinearImageDataset(_parse(scene))[0]
    assert "gt_clean" not in item and "gt_depth" not in item and "depth_image" in item


def test_ground_truth_for_some_frames_or_missing_files_is_a_clear_error(tmp_path):
    from seathru_nerfstudio.data.nerfstudio_data import GroundTruthError

    scene = _synth_scene(tmp_path)
    _edit_frames(scene, lambda index, frame: frame.pop("gt_depth_file_path") if index == 0 else None)
    with pytest.raises(GroundTruthError, match=r"transforms.json: 2 of 3 frames have 'gt_depth_file_path'"):
        _parse(scene)
    scene = _synth_scene(tmp_path, "other")
    (scene / "ground_truth" / "clean" / "frame_00002.png").unlink()
    with pytest.raises(GroundTruthError, match=r"gt_clean_file_path names 1 missing file\(s\): .*frame_00002.png"):
        _parse(scene)
