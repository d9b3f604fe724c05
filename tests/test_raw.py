"""RAW decoding and white balance: synthetic RGGB mosaics written as DNG (pidng), decoded
by rawpy through seathru-process-data, compared with the known linear image."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2  # before anything that loads pycolmap (see seathru_nerfstudio/data/sfm.py)
import numpy as np
import pytest
import rawpy
from pidng.core import RAW2DNG, DNGTags, Tag
from pidng.defs import CalibrationIlluminant, CFAPattern, DNGVersion, Orientation, PhotometricInterpretation

from seathru_nerfstudio.data.linear_images import read_linear_image
from seathru_nerfstudio.data.process import ProcessSeathruData, process
from seathru_nerfstudio.data.raw import (
    ChannelHistogram,
    RawDecodeError,
    decode_raw,
    downscale_to_long_side,
    estimate_white_balance,
)

import forked_cli

H, W = 64, 96
BLACK, WHITE = 512, 16383  # 14-bit sensor in a 16-bit container
BORDER = 4  # demosaicing is only accurate away from the image edge


def smooth_linear_image(seed: int, scale: tuple[float, float, float] = (0.35, 0.6, 0.8)) -> np.ndarray:
    """A smooth (demosaic-friendly) linear RGB image in (0, 1), channel means ~ ``scale``."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    channels = []
    for c in range(3):
        fx, fy, phase = rng.uniform(1 / 24, 1 / 12), rng.uniform(1 / 24, 1 / 12), rng.uniform(0, 6)
        wave = 0.5 + 0.35 * np.sin(xx * fx + phase) * np.cos(yy * fy - phase)
        channels.append(scale[c] * wave)
    return np.clip(np.stack(channels, axis=-1), 0.01, 0.99)


def write_bayer_dng(path: Path, linear: np.ndarray, as_shot_neutral=(1.0, 1.0, 1.0)) -> None:
    """Mosaic ``linear`` (H, W, 3) with an RGGB pattern and write it as an uncompressed DNG."""
    mosaic = np.empty(linear.shape[:2])
    mosaic[0::2, 0::2] = linear[0::2, 0::2, 0]
    mosaic[0::2, 1::2] = linear[0::2, 1::2, 1]
    mosaic[1::2, 0::2] = linear[1::2, 0::2, 1]
    mosaic[1::2, 1::2] = linear[1::2, 1::2, 2]
    raw = np.round(BLACK + mosaic * (WHITE - BLACK)).astype(np.uint16)
    height, width = raw.shape
    tags = DNGTags()
    tags.set(Tag.ImageWidth, width)
    tags.set(Tag.ImageLength, height)
    tags.set(Tag.TileWidth, width)
    tags.set(Tag.TileLength, height)
    tags.set(Tag.Orientation, Orientation.Horizontal)
    tags.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    tags.set(Tag.SamplesPerPixel, 1)
    tags.set(Tag.BitsPerSample, 16)
    tags.set(Tag.CFARepeatPatternDim, [2, 2])
    tags.set(Tag.CFAPattern, CFAPattern.RGGB)
    tags.set(Tag.BlackLevel, BLACK)
    tags.set(Tag.WhiteLevel, WHITE)
    tags.set(Tag.ColorMatrix1, [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]])
    tags.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    tags.set(Tag.AsShotNeutral, [[int(round(v * 1000)), 1000] for v in as_shot_neutral])
    tags.set(Tag.Make, "seathru")
    tags.set(Tag.Model, "synthetic bayer")
    tags.set(Tag.DNGVersion, DNGVersion.V1_4)
    tags.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)
    writer = RAW2DNG()
    writer.options(tags, path="", compress=False)
    writer.convert(raw, filename=str(path.with_suffix("")))
    assert path.with_suffix(".dng").is_file()


def interior(image: np.ndarray) -> np.ndarray:
    return image[BORDER:-BORDER, BORDER:-BORDER]


def tree_hash(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def test_pidng_dng_is_read_back_by_rawpy(tmp_path: Path) -> None:
    truth = smooth_linear_image(0)
    write_bayer_dng(tmp_path / "a.dng", truth)
    with rawpy.imread(str(tmp_path / "a.dng")) as raw:
        assert raw.raw_image_visible.shape == (H, W)
        assert raw.color_desc == b"RGBG"
        assert raw.raw_pattern.tolist() == [[0, 1], [3, 2]]  # R G / G B
        assert raw.white_level == WHITE
        assert list(raw.black_level_per_channel) == [BLACK] * 4
        assert raw.raw_image_visible[0, 0] == round(BLACK + truth[0, 0, 0] * (WHITE - BLACK))


def test_decode_raw_is_linear_camera_rgb(tmp_path: Path) -> None:
    truth = smooth_linear_image(1)
    write_bayer_dng(tmp_path / "a.dng", truth, as_shot_neutral=(0.5, 1.0, 0.8))
    decoded = decode_raw(tmp_path / "a.dng")
    assert decoded.dtype == np.float32 and decoded.shape == (H, W, 3)
    # No gamma, no auto-brightening, no white balance (the file's as-shot WB is ignored):
    # black level -> 0, white level -> 1, linear in between.
    error = np.abs(interior(decoded) - interior(truth))
    assert error.max() < 4e-3, error.max()
    # 16-bit output, not 8-bit: values are not on a 1/255 grid
    assert np.unique(np.round(decoded * 65535)).size > 1000


def test_decode_raw_with_camera_white_balance(tmp_path: Path) -> None:
    truth = smooth_linear_image(2, scale=(0.3, 0.6, 0.4))
    write_bayer_dng(tmp_path / "a.dng", truth, as_shot_neutral=(0.5, 1.0, 0.8))
    decoded = decode_raw(tmp_path / "a.dng", use_camera_wb=True)
    ratio = np.median(interior(decoded) / interior(truth), axis=(0, 1))
    np.testing.assert_allclose(ratio / ratio[1], [2.0, 1.0, 1.25], rtol=0.01)


def test_corrupt_raw_raises_naming_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "broken.NEF"
    bad.write_bytes(b"not a raw file" * 100)
    with pytest.raises(RawDecodeError, match="broken.NEF"):
        decode_raw(bad)


def test_joint_percentile_white_balance_matches_numpy() -> None:
    images = [smooth_linear_image(s) * f for s, f in [(3, 1.0), (4, 0.7), (5, 1.2)]]
    images = [np.clip(im, 0, 1) for im in images]
    histogram = ChannelHistogram()
    for image in images:
        histogram.add(image)
    wb = estimate_white_balance(histogram, "percentile", 0.5)
    stacked = np.concatenate([im.reshape(-1, 3) for im in images])
    order_statistic = dict(axis=0, method="inverted_cdf")  # the histogram's exact definition
    np.testing.assert_allclose(wb.low, np.percentile(stacked, 0.5, **order_statistic), atol=1 / 65535)
    np.testing.assert_allclose(wb.high, np.percentile(stacked, 99.5, **order_statistic), atol=1 / 65535)
    np.testing.assert_allclose(wb.gains, 1.0 / np.asarray(wb.high), rtol=1e-9)
    balanced = np.concatenate([wb.apply(im.astype(np.float32)).reshape(-1, 3) for im in images])
    # every channel: 99.5% point at 1, nothing above 1, the lowest 0.5% clipped to one value
    np.testing.assert_allclose(np.percentile(balanced, 99.5, axis=0), 1.0, atol=1e-3)
    assert balanced.max() <= 1.0 + 1e-6
    np.testing.assert_allclose(balanced.min(axis=0), np.asarray(wb.low) * wb.gains, rtol=1e-5)
    # linear: between the clip points the map is a pure per-channel gain (no offset)
    inside = (stacked > wb.low) & (stacked < wb.high)
    np.testing.assert_allclose((balanced / stacked)[inside[:, 0], 0], wb.gains[0], rtol=1e-5)


def test_grey_world_equalises_channel_means() -> None:
    image = smooth_linear_image(6, scale=(0.2, 0.5, 0.7))
    histogram = ChannelHistogram()
    histogram.add(image)
    wb = estimate_white_balance(histogram, "grey-world", 0.5)
    balanced = wb.apply(image.astype(np.float32))
    means = balanced.reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(means / means.mean(), 1.0, atol=2e-3)
    assert balanced.max() == pytest.approx(1.0, abs=1e-6)


def test_downscale_is_area_average() -> None:
    image = smooth_linear_image(7).astype(np.float32)
    small = downscale_to_long_side(image, W // 2)
    assert small.shape == (H // 2, W // 2, 3)
    blocks = image.reshape(H // 2, 2, W // 2, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(small, blocks, atol=1e-6)
    assert downscale_to_long_side(image, 10 * W) is image  # never upscales


@pytest.mark.parametrize("method", ["none", "percentile"])
def test_process_raw_folder_matches_truth(tmp_path: Path, method: str) -> None:
    """DNG folder -> seathru-process-data (no SfM) -> 16-bit PNGs equal the known linear
    images, before (``none``) and after the joint percentile white balance."""
    data = tmp_path / "raw"
    data.mkdir()
    truths = {}
    for i, (seed, exposure) in enumerate([(10, 1.0), (11, 0.6), (12, 0.8)]):
        truths[f"IMG_{i}"] = np.clip(smooth_linear_image(seed, scale=(0.25, 0.55, 0.7)) * exposure, 0, 1)
        write_bayer_dng(data / f"IMG_{i}.dng", truths[f"IMG_{i}"], as_shot_neutral=(0.6, 1.0, 0.9))
    before = tree_hash(data)

    report = process(ProcessSeathruData(data=data, output_dir=tmp_path / "out", white_balance=method, skip_sfm=True))

    assert tree_hash(data) == before  # the user's files are never modified
    assert report.images == ["IMG_0.png", "IMG_1.png", "IMG_2.png"]
    saved = json.loads((tmp_path / "out" / "white_balance.json").read_text())
    assert saved["method"] == method
    if method == "percentile":
        stacked = np.concatenate([interior(t).reshape(-1, 3) for t in truths.values()])
        np.testing.assert_allclose(saved["gains"], 1 / np.percentile(stacked, 99.5, axis=0), rtol=0.02)
    low, high, gains = (np.asarray(saved[k]) for k in ("low", "high", "gains"))
    for stem, truth in truths.items():
        png = cv2.imread(str(tmp_path / "out" / "images" / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16
        out = read_linear_image(tmp_path / "out" / "images" / f"{stem}.png")
        expected = truth if method == "none" else np.clip(truth, low, high) * gains
        # compared in sensor units (divided by the gains, which also scale the demosaic error)
        error = np.abs(interior(out) - interior(expected)) / (gains if method != "none" else 1.0)
        assert error.max() < 4e-3 and error.mean() < 5e-4, (stem, error.max(), error.mean())


def test_corrupt_raw_is_skipped_with_a_warning_and_listed(tmp_path: Path) -> None:
    """One unreadable file among good ones: the run goes on (exit 0), names it, leaves it out."""
    data = tmp_path / "raw"
    data.mkdir()
    for i in range(2):
        write_bayer_dng(data / f"good_{i}.dng", smooth_linear_image(20 + i))
    (data / "bad.dng").write_bytes(b"\x00garbage" * 64)
    before = tree_hash(data)
    run = forked_cli.run_in_a_folder_of_its_own(
        "seathru-process-data", "--data", data, "--output-dir", tmp_path / "out", "--skip-sfm", timeout_s=300, streams_apart=True
    )
    assert run.returncode == 0, run.output
    assert "bad.dng" in run.stdout and "Warning" in run.stdout
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == ["good_0.png", "good_1.png"]
    assert tree_hash(data) == before


def test_all_raws_corrupt_is_an_error(tmp_path: Path) -> None:
    data = tmp_path / "raw"
    data.mkdir()
    for name in ("a.NEF", "b.CR2"):
        (data / name).write_bytes(b"junk" * 100)
    run = forked_cli.run_in_a_folder_of_its_own(
        "seathru-process-data", "--data", data, "--output-dir", tmp_path / "out", "--skip-sfm", timeout_s=300, streams_apart=True
    )
    assert run.returncode != 0
    assert "none of the 2 files" in run.stdout and "a.NEF" in run.stdout
    assert not (tmp_path / "out").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]  # no half-built sibling either
