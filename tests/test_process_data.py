"""``seathru-process-data`` as users run it (a process of its own): bad input gets a clear message and
a non-zero exit, nothing half-written, and the input folder is never touched."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from seathru_nerfstudio.data import process as process_module
from seathru_nerfstudio.data.process import ProcessDataError, ProcessSeathruData, process
from seathru_nerfstudio.data.sfm import SfmError

import forked_cli

def run_cli(*args: str | Path) -> forked_cli.Result:
    """``seathru-process-data *args`` in a process of its own (``forked_cli``: its imports are paid
    once per test run, not per call); ``message`` is its output on one line (rich wraps long lines)."""
    result = forked_cli.run_in_a_folder_of_its_own("seathru-process-data", *args, timeout_s=300)
    result.message = " ".join(result.output.split())
    return result


def write_png16(path: Path, height: int = 48, width: int = 64, seed: int = 0) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.random.default_rng(seed).integers(0, 65535, (height, width, 3), dtype=np.uint16)
    assert cv2.imwrite(str(path), image)


def tree_hash(folder: Path) -> dict[str, str]:
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def assert_nothing_written(parent: Path, keep: set[str]) -> None:
    """Only the folders the test made exist: no output, no hidden build folder."""
    assert {p.name for p in parent.iterdir()} == keep


def test_empty_folder(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "notes.txt").write_text("not an image")
    result = run_cli("--data", tmp_path / "in", "--output-dir", tmp_path / "out")
    assert result.returncode != 0
    assert "holds no RAW" in result.message and ".nef" in result.message
    assert_nothing_written(tmp_path, {"in"})


def test_missing_folder(tmp_path: Path) -> None:
    result = run_cli("--data", tmp_path / "nope", "--output-dir", tmp_path / "out")
    assert result.returncode != 0 and "is not a folder" in result.message
    assert_nothing_written(tmp_path, set())


def test_mixed_image_sizes(tmp_path: Path) -> None:
    write_png16(tmp_path / "in" / "a.png", 48, 64)
    write_png16(tmp_path / "in" / "b.png", 48, 64)
    write_png16(tmp_path / "in" / "c.png", 64, 48)
    before = tree_hash(tmp_path / "in")
    result = run_cli("--data", tmp_path / "in", "--output-dir", tmp_path / "out", "--skip-sfm")
    assert result.returncode != 0
    assert "same size" in result.message and "64x48: a.png, b.png" in result.message and "48x64: c.png" in result.message
    assert_nothing_written(tmp_path, {"in"})
    assert tree_hash(tmp_path / "in") == before


def test_8bit_images_are_refused(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    cv2.imwrite(str(tmp_path / "in" / "a.png"), np.zeros((8, 8, 3), np.uint8))
    result = run_cli("--data", tmp_path / "in", "--output-dir", tmp_path / "out", "--skip-sfm")
    assert result.returncode != 0 and "8-bit" in result.message and "not linear" in result.message
    assert_nothing_written(tmp_path, {"in"})


@pytest.mark.parametrize("second", ["a.tif", "b.NEF"])
def test_ambiguous_folders(tmp_path: Path, second: str) -> None:
    write_png16(tmp_path / "in" / "a.png")
    (tmp_path / "in" / second).write_bytes(b"x")
    result = run_cli("--data", tmp_path / "in", "--output-dir", tmp_path / "out", "--skip-sfm")
    assert result.returncode != 0
    assert ("would both become a.png" in result.message) or ("mixes RAW files" in result.message)
    assert_nothing_written(tmp_path, {"in"})


def test_output_with_results_needs_overwrite(tmp_path: Path) -> None:
    for i in range(2):
        write_png16(tmp_path / "in" / f"f{i}.png", seed=i)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "transforms.json").write_text("{}")
    before_in, before_out = tree_hash(tmp_path / "in"), tree_hash(tmp_path / "out")

    refused = run_cli("--data", tmp_path / "in", "--output-dir", tmp_path / "out", "--skip-sfm")
    assert refused.returncode != 0 and "already holds files" in refused.message and "--overwrite" in refused.message
    assert tree_hash(tmp_path / "out") == before_out

    replaced = run_cli("--data", tmp_path / "in", "--output-dir", tmp_path / "out", "--skip-sfm", "--overwrite")
    assert replaced.returncode == 0, replaced.message
    assert sorted(tree_hash(tmp_path / "out")) == ["images/f0.png", "images/f1.png", "white_balance.json"]
    assert tree_hash(tmp_path / "in") == before_in
    assert_nothing_written(tmp_path, {"in", "out"})


def test_output_inside_out_relation_with_input_is_refused(tmp_path: Path) -> None:
    write_png16(tmp_path / "in" / "a.png")
    result = run_cli("--data", tmp_path / "in", "--output-dir", tmp_path / "in", "--overwrite", "--skip-sfm")
    assert result.returncode != 0 and "would contain the input folder" in result.message
    assert sorted(tree_hash(tmp_path / "in")) == ["a.png"]


def test_images_that_do_not_register(tmp_path: Path) -> None:
    """Unrelated noise frames: SfM finds no model -> error, exit 1, nothing written."""
    for i in range(4):
        write_png16(tmp_path / "in" / f"noise_{i}.png", 120, 160, seed=10 + i)
    before = tree_hash(tmp_path / "in")
    result = run_cli("--data", tmp_path / "in", "--output-dir", tmp_path / "out")
    assert result.returncode != 0
    assert "registered none of the 4 images" in result.message
    assert "Failed to create any sparse model" not in result.message  # COLMAP's own log line: ours says it
    assert_nothing_written(tmp_path, {"in"})
    assert tree_hash(tmp_path / "in") == before


def test_failed_overwrite_keeps_previous_results(tmp_path: Path, monkeypatch) -> None:
    """A run that dies late (here: in SfM) leaves the previous dataset exactly as it was."""
    for i in range(3):
        write_png16(tmp_path / "in" / f"f{i}.png", seed=i)
    (tmp_path / "out" / "images").mkdir(parents=True)
    (tmp_path / "out" / "images" / "old.png").write_bytes(b"previous run")
    before = tree_hash(tmp_path / "out")

    def fail(*args, **kwargs):
        raise SfmError("simulated failure after the images were written")

    monkeypatch.setattr(process_module, "run_sfm", fail)
    with pytest.raises(SfmError, match="simulated"):
        process(ProcessSeathruData(data=tmp_path / "in", output_dir=tmp_path / "out", overwrite=True))
    assert tree_hash(tmp_path / "out") == before
    assert_nothing_written(tmp_path, {"in", "out"})


def test_bad_options(tmp_path: Path) -> None:
    write_png16(tmp_path / "in" / "a.png")
    with pytest.raises(ProcessDataError, match="clip-percent"):
        process(ProcessSeathruData(data=tmp_path / "in", output_dir=tmp_path / "out", clip_percent=60))
    with pytest.raises(ProcessDataError, match="needs RAW files"):
        process(ProcessSeathruData(data=tmp_path / "in", output_dir=tmp_path / "out", white_balance="camera"))
    for focal in (0.0, -100.0, float("nan")):
        with pytest.raises(ProcessDataError, match="--focal-length-px must be a positive number of pixels"):
            process(ProcessSeathruData(data=tmp_path / "in", output_dir=tmp_path / "out", focal_length_px=focal))
    assert_nothing_written(tmp_path, {"in"})


def test_16bit_png_input_round_trips_exactly(tmp_path: Path) -> None:
    """No white balance: 16-bit linear PNG in -> identical 16-bit PNG out (lossless path)."""
    write_png16(tmp_path / "in" / "a.png", seed=3)
    process(ProcessSeathruData(data=tmp_path / "in", output_dir=tmp_path / "out", white_balance="none", skip_sfm=True))
    source = cv2.imread(str(tmp_path / "in" / "a.png"), cv2.IMREAD_UNCHANGED)
    result = cv2.imread(str(tmp_path / "out" / "images" / "a.png"), cv2.IMREAD_UNCHANGED)
    assert result.dtype == np.uint16 and np.array_equal(source, result)
    shutil.rmtree(tmp_path / "out")


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_output_folder_and_files_follow_the_umask(tmp_path: Path, umask: int) -> None:
    """As a plain mkdir/open would make them, not tempfile's 0700/0600."""
    from seathru_nerfstudio.data.io import write_text_atomic

    write_png16(tmp_path / "in" / "a.png", seed=3)
    previous = os.umask(umask)
    try:
        process(ProcessSeathruData(data=tmp_path / "in", output_dir=tmp_path / "out", white_balance="none", skip_sfm=True))
        write_text_atomic(tmp_path / "out" / "note.txt", "x")
    finally:
        os.umask(previous)
    for folder in (tmp_path / "out", tmp_path / "out" / "images"):
        assert folder.stat().st_mode & 0o777 == 0o777 & ~umask, folder
    for file in (tmp_path / "out" / "white_balance.json", tmp_path / "out" / "note.txt"):
        assert file.stat().st_mode & 0o777 == 0o666 & ~umask, file


def test_identical_images_are_refused_naming_them(tmp_path: Path) -> None:
    write_png16(tmp_path / "in" / "a.png", seed=1)
    write_png16(tmp_path / "in" / "b.png", seed=2)
    shutil.copy(tmp_path / "in" / "a.png", tmp_path / "in" / "c.png")
    with pytest.raises(ProcessDataError, match=r"identical images: a.png = c.png\. .*camera to move"):
        process(ProcessSeathruData(data=tmp_path / "in", output_dir=tmp_path / "out"))
    assert_nothing_written(tmp_path, {"in"})
    with pytest.raises(ProcessDataError, match="--min-registered-fraction must be in"):
        process(ProcessSeathruData(data=tmp_path / "in", output_dir=tmp_path / "out", min_registered_fraction=1.5))
