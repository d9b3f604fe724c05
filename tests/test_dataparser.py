"""``seathru-data`` on a miniature dataset in the published SeaThru-NeRF layout
(images_wb/, sparse/0 written by pycolmap, poses_bounds.npy)."""

from __future__ import annotations

from pathlib import Path

import cv2  # before pycolmap (see seathru_nerfstudio/data/sfm.py)
import numpy as np
import pycolmap
import pytest
import torch

from seathru_nerfstudio.data.linear_images import LinearImageDataset
from seathru_nerfstudio.data.nerfstudio_data import EXTENT_KEY
from seathru_nerfstudio.data.seathru_dataparser import SeathruDataError, SeathruDataParserConfig
from seathru_nerfstudio.data.sfm_outputs import llff_poses_bounds


WIDTH, HEIGHT = 1700, 6  # wider than nerfstudio's 1600 px auto-downscale threshold
NAMES = [f"img_{i:02d}.png" for i in range(10)]
FX, FY, CX, CY, K1, K2, P1, P2 = 1500.0, 1400.0, 851.0, 3.2, 0.01, -0.002, 0.001, 0.0005
NEAR = np.array([1.0 + 0.1 * i for i in range(len(NAMES))])
FAR = np.array([10.0 + i for i in range(len(NAMES))])


def write_png16(path: Path, rgb_codes: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), rgb_codes.astype(np.uint16)[..., ::-1])


def make_reconstruction(names: list[str]) -> pycolmap.Reconstruction:
    """One OPENCV camera; camera i at x = 0.1 i looking down +z; 3D points at depth 2..5 m.
    Image ids run against name order, so COLMAP order != sorted-name order."""
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera(camera_id=1, model="OPENCV", width=WIDTH, height=HEIGHT, params=[FX, FY, CX, CY, K1, K2, P1, P2])
    rec.add_camera_with_trivial_rig(camera)
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-1, 1, 40), rng.uniform(-1, 1, 40), np.linspace(2.0, 5.0, 40)])
    for k, name in enumerate(names):
        image_id = len(names) - k
        centre = np.array([0.1 * k, 0.0, 0.0])
        image = pycolmap.Image(name=name, keypoints=np.zeros((len(points), 2)), camera_id=1, image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(), -centre))
    for j, xyz in enumerate(points):
        track = pycolmap.Track()
        for image_id in rec.images:
            track.add_element(image_id, j)
        rec.add_point3D(xyz, track, np.array([128, 128, 128], dtype=np.uint8))
    return rec


def make_dataset(
    root: Path,
    image_dir: str = "images_wb",
    disk_names: list[str] | None = None,
    colmap_names: list[str] | None = None,
    poses_bounds: bool = True,
) -> Path:
    rec = make_reconstruction(colmap_names or NAMES)
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    rec.write(sparse)
    for k, name in enumerate(disk_names or NAMES):
        write_png16(root / image_dir / name, np.full((HEIGHT, WIDTH, 3), 1000 * (k + 1)))
    if poses_bounds:
        _, rows = llff_poses_bounds(rec)
        rows[:, 15], rows[:, 16] = NEAR, FAR
        np.save(root / "poses_bounds.npy", rows)
    return root


def parse(root: Path, split: str = "train", **config):
    return SeathruDataParserConfig(data=root, **config).setup().get_dataparser_outputs(split)


def test_published_split_intrinsics_near_far_and_no_downscale(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "scene")
    train, test = parse(root, "train"), parse(root, "test")

    assert [p.name for p in test.image_filenames] == ["img_00.png", "img_08.png"]  # index % 8 == 0
    assert [p.name for p in train.image_filenames] == [n for i, n in enumerate(NAMES) if i % 8 != 0]
    assert all(p.parent.name == "images_wb" for p in train.image_filenames)  # not images_wb_2

    cameras = train.cameras
    assert torch.all(cameras.width == WIDTH) and torch.all(cameras.height == HEIGHT)
    for value, expected in [(cameras.fx, FX), (cameras.fy, FY), (cameras.cx, CX), (cameras.cy, CY)]:
        assert torch.allclose(value, torch.tensor(expected), rtol=1e-6)
    assert torch.allclose(cameras.distortion_params[0], torch.tensor([K1, K2, 0.0, 0.0, P1, P2]))

    scale = float(train.dataparser_scale)
    assert scale != 1.0  # poses were rescaled, so near/far must be too
    train_idx = [i for i in range(len(NAMES)) if i % 8 != 0]
    expected = torch.tensor(np.stack([NEAR, FAR], 1)[train_idx] * scale, dtype=torch.float32)
    assert torch.allclose(train.metadata["near_far"], expected, rtol=1e-5)
    assert torch.allclose(test.metadata["near_far"][:, 0], torch.tensor(NEAR[[0, 8]] * scale, dtype=torch.float32))
    assert train.metadata["near_plane"] == pytest.approx(NEAR.min() * scale)
    assert train.metadata["far_plane"] == pytest.approx(FAR.max() * scale)
    # the contraction's extent holds every view up to the far bound, and little more
    far, c2w, cams = train.metadata["far_plane"], train.cameras.camera_to_worlds, train.cameras
    on_axis = c2w[:, :3, 3] - c2w[:, :3, 2] * far  # the optical axis at z-depth far (cameras look along -z)
    half_u = torch.maximum(cams.cx, cams.width - cams.cx) / cams.fx
    half_v = torch.maximum(cams.cy, cams.height - cams.cy) / cams.fy
    corner_norm = float(torch.sqrt(half_u**2 + half_v**2 + 1).max())
    extent = train.metadata[EXTENT_KEY]
    assert float(on_axis.abs().max()) <= extent * (1 + 1e-6)  # float32 poses
    assert extent <= float(c2w[:, :3, 3].abs().max()) + far * corner_norm + 1e-5

    # camera centres keep their spacing: consecutive names 0.1 COLMAP units apart, times the scale
    centres = train.cameras.camera_to_worlds[:, :3, 3]
    assert torch.linalg.norm(centres[1] - centres[0]).item() == pytest.approx(0.1 * scale, rel=1e-4)


def test_linear_16bit_values_survive_to_the_loaded_tensor(tmp_path: Path) -> None:
    """Pixel values that differ only in the low byte still differ after dataparser + dataset."""
    root = make_dataset(tmp_path / "scene")
    codes = np.full((HEIGHT, WIDTH, 3), 0x1200, dtype=np.uint16)
    codes[0, 1] = 0x1201
    codes[0, 2] = 0x12FF
    write_png16(root / "images_wb" / "img_01.png", codes)
    outputs = parse(root, "train")
    index = [p.name for p in outputs.image_filenames].index("img_01.png")
    image = LinearImageDataset(outputs)[index]["image"]
    assert image.dtype == torch.float32 and image.shape == (HEIGHT, WIDTH, 3)
    px = image[0, :3, 0].double() * 65535.0
    assert torch.allclose(px, torch.tensor([0x1200, 0x1201, 0x12FF], dtype=torch.float64), atol=1e-2)
    assert px[0] != px[1]  # an 8-bit path would make these equal (same high byte)


def test_capitalised_images_wb_folder(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "scene", image_dir="Images_wb")
    assert parse(root).image_filenames[0].parent.name == "Images_wb"


def test_colmap_names_with_another_extension_match_by_stem(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "scene", colmap_names=[n.replace(".png", ".JPG") for n in NAMES])
    assert [p.name for p in parse(root, "test").image_filenames] == ["img_00.png", "img_08.png"]


def test_name_mismatch_names_both_sides(tmp_path: Path) -> None:
    disk = NAMES[:-1] + ["extra_frame.png"]
    root = make_dataset(tmp_path / "scene", disk_names=disk)
    with pytest.raises(SeathruDataError) as error:
        parse(root)
    message = str(error.value)
    assert "In COLMAP but not in images_wb/ (1): img_09.png" in message
    assert "In images_wb/ but not in COLMAP (1): extra_frame.png" in message


def test_requested_downscale_needs_existing_linear_folder(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "scene")
    with pytest.raises(SeathruDataError, match="images_wb_2"):
        parse(root, downscale_factor=2)
    for k, name in enumerate(NAMES):
        write_png16(root / "images_wb_2" / name, np.full((HEIGHT // 2, WIDTH // 2, 3), 1000 * (k + 1)))
    outputs = parse(root, downscale_factor=2)
    assert outputs.image_filenames[0].parent.name == "images_wb_2"
    assert torch.all(outputs.cameras.width == WIDTH // 2)


def test_poses_bounds_row_count_must_match(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "scene")
    np.save(root / "poses_bounds.npy", np.load(root / "poses_bounds.npy")[:-1])
    with pytest.raises(SeathruDataError, match="9 rows but .* has 10 images"):
        parse(root)


def test_poses_bounds_in_another_order_warns(tmp_path: Path, capsys) -> None:
    root = make_dataset(tmp_path / "scene")
    rows = np.load(root / "poses_bounds.npy")
    np.save(root / "poses_bounds.npy", rows[[2, 0, 1, *range(3, len(rows))]])
    parse(root)
    assert "do not match" in " ".join(capsys.readouterr().out.split())  # rich wraps lines


def test_near_far_from_sparse_points_without_poses_bounds(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "scene", poses_bounds=False)
    outputs = parse(root)
    scale = float(outputs.dataparser_scale)
    near_far = outputs.metadata["near_far"] / scale  # back to COLMAP units: points at depth 2..5
    assert torch.allclose(near_far[:, 0], torch.tensor(2.0), atol=0.01)
    assert torch.allclose(near_far[:, 1], torch.tensor(5.0), atol=0.01)


def test_missing_layout_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "scene" / "sparse" / "0").mkdir(parents=True)
    with pytest.raises(SeathruDataError, match="no image folder"):
        parse(tmp_path / "scene")
    root = make_dataset(tmp_path / "full")
    with pytest.raises(SeathruDataError, match="looked for typo/$"):  # a folder the user named must exist
        parse(root, images_path=Path("typo"))


def test_registered_as_nerfstudio_dataparser() -> None:
    from nerfstudio.plugins.registry_dataparser import discover_dataparsers

    dataparsers, descriptions = discover_dataparsers()
    assert isinstance(dataparsers["seathru-data"], SeathruDataParserConfig)
    assert "every 8th" in descriptions["seathru-data"]


# --------------------------------------------------------------- checks at load (issue 37)
def test_seathru_data_refuses_an_image_of_another_size_naming_it(tmp_path: Path) -> None:
    from seathru_nerfstudio.input_errors import InputError

    root = make_dataset(tmp_path / "scene")
    write_png16(root / "images_wb" / NAMES[3], np.full((HEIGHT, WIDTH - 2, 3), 1000))
    with pytest.raises(InputError, match=rf"images_wb/{NAMES[3]} is {WIDTH - 2}×{HEIGHT} px, but its camera is {WIDTH}×{HEIGHT}"):
        parse(root)


def transforms_folder(root: Path, frames: list, **top) -> Path:
    import json

    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms.json").write_text(json.dumps({"fl_x": 10.0, "fl_y": 10.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "frames": frames, **top}))
    return root


def frame(name: str, **extra) -> dict:
    return {"file_path": name, "transform_matrix": np.eye(4).tolist(), **extra}


@pytest.mark.parametrize(
    "frames, top, message",
    [
        ([{"transform_matrix": np.eye(4).tolist()}], {}, 'frame 0 has no "file_path"'),
        ([frame("a.png", transform_matrix=[[1, 0], [0, 1]])], {}, r"frame 0 \(a.png\): transform_matrix is of shape \(2, 2\)"),
        ([frame("a.png", transform_matrix=np.diag([1.0, 1.0, float("inf"), 1.0]).tolist())], {}, r"transform_matrix\[2\]\[2\] is inf"),
        ([frame("a.png"), frame("b.png", depth_file_path="d.png")], {}, r"frame 0 \(a.png\) has no 'depth_file_path', but 1 of the 2"),
        ([frame("a.png")], {"fl_x": float("nan")}, "the top level: fl_x is nan"),
        ([frame("a.png", w=0)], {}, r"frame 0 \(a.png\): w is 0; expected a finite number > 0"),
        ([frame("a.png")], {"train_filenames": ["zz.png"]}, "train_filenames lists 1 image"),
        ([frame("missing.png")], {}, r"file_path missing.png does not exist"),
    ],
)
def test_transforms_json_problems_name_the_frame_and_field(tmp_path: Path, frames, top, message) -> None:
    from seathru_nerfstudio.data.input_checks import DatasetError, load_transforms

    root = transforms_folder(tmp_path / "scene", frames, **top)
    for name in ("a.png", "b.png", "d.png"):
        write_png16(root / name, np.full((6, 8, 3), 1000))
    with pytest.raises(DatasetError, match=message) as error:
        load_transforms(root)
    assert str(root / "transforms.json") in str(error.value)


def test_an_image_is_checked_again_once_it_changes(tmp_path: Path) -> None:
    """The check is cached per file version: a file rewritten with other pixels is read again."""
    import os

    from seathru_nerfstudio.data.input_checks import DatasetError, check_images

    path = tmp_path / "a.png"
    write_png16(path, np.full((6, 8, 3), 1000))
    check_images([path], [6], [8])
    write_png16(path, np.zeros((6, 8, 3)))
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 1))  # whatever the clock's resolution
    with pytest.raises(DatasetError, match="all black"):
        check_images([path], [6], [8])
    with pytest.raises(DatasetError, match=r"is 8×6 px, but its camera is 9×6"):
        write_png16(path, np.full((6, 8, 3), 1000))
        os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 2))
        check_images([path], [6], [9])
