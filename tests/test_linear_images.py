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


def test_sparse_depth_images_reach_the_batch_in_scene_units(tmp_path):
    """seathru-synth's SfM-like depth/ (nerfstudio's depth_file_path, mm) arrives as
    ``depth_image`` in scene units, and the parser tells the model its scale."""
    import cv2

    from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY, SeathruNerfstudioDataParserConfig
    from seathru_nerfstudio.data.synthetic import SynthConfig, generate

    scene = generate(SynthConfig(output_dir=tmp_path / "s", width=24, height=16, num_views=3, sfm_points_per_view=20))
    outputs = SeathruNerfstudioDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    scale = float(outputs.dataparser_scale)
    assert outputs.metadata[SCALE_KEY] == scale
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
