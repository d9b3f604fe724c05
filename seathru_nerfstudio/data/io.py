"""Writing what our data commands produce: 16-bit linear PNGs, and output folders that
appear whole or not at all.

* Images: linear values in [0, 1] are stored as ``round(value * 65535)`` in a 16-bit PNG, RGB
  channel order (OpenCV's BGR is swapped here), no gamma, no sRGB chunk.
* Folders: :func:`atomic_output_folder` builds everything in a hidden sibling
  (``.<name>.partial-*``) and renames it into place when the build succeeds; an interrupted or
  failed build leaves no half-written folder, and the folder it replaces (``--overwrite``)
  stays untouched until the last moment.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import numpy.typing as npt


class OutputFolderError(ValueError):
    """The output folder cannot be written (it is a file, or it holds files and may not be replaced)."""


def to_uint16(image: npt.NDArray[np.floating]) -> npt.NDArray[np.uint16]:
    """Quantise linear [0, 1] values to 16-bit code values (round to nearest, clipped)."""
    return np.round(np.clip(image, 0.0, 1.0) * 65535.0).astype(np.uint16)


def _write_png(path: Path, codes: npt.NDArray[np.uint16]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(codes)):
        raise OSError(f"{path}: could not write image")


def write_png16(path: Path, rgb: npt.NDArray[np.floating]) -> None:
    """Write a linear RGB image ``(H, W, 3)`` in [0, 1] as a 16-bit PNG."""
    _write_png(path, to_uint16(rgb)[..., ::-1])


def write_png16_gray(path: Path, codes: npt.NDArray[np.integer]) -> None:
    """Write 16-bit code values ``(H, W)`` (e.g. depth in millimetres) as a one-channel PNG."""
    _write_png(path, codes.astype(np.uint16))


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file beside ``path``, then rename it over ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.partial-", dir=path.parent)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as file:
            file.write(text)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def check_output_folder(folder: Path, overwrite: bool) -> None:
    """Raise :class:`OutputFolderError` unless ``folder`` is missing, empty, or may be replaced."""
    if folder.exists() and not folder.is_dir():
        raise OutputFolderError(f"--output-dir {folder} exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise OutputFolderError(
            f"{folder} already holds files. Pass --overwrite to replace it, or choose another --output-dir"
        )


@contextlib.contextmanager
def atomic_output_folder(folder: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield an empty hidden sibling of ``folder`` to build in; when the block ends without an
    error, it becomes ``folder`` (replacing what was there, which needs ``overwrite`` unless the
    folder is missing or empty). On an error the build is deleted and ``folder`` is untouched.

    Raises :class:`OutputFolderError` before the block runs, and again before the swap (the
    folder may have been filled meanwhile), when ``folder`` may not be written.
    """
    folder = Path(folder)
    check_output_folder(folder, overwrite)
    folder.parent.mkdir(parents=True, exist_ok=True)
    build = Path(tempfile.mkdtemp(prefix=f".{folder.name}.partial-", dir=folder.parent))
    try:
        yield build
        check_output_folder(folder, overwrite)
        _swap_in(build, folder)
    except BaseException:
        shutil.rmtree(build, ignore_errors=True)
        raise


def _swap_in(build: Path, folder: Path) -> None:
    """Rename ``build`` to ``folder``; a previous ``folder`` is moved aside first and deleted last."""
    previous = None
    if folder.is_dir():
        if any(folder.iterdir()):
            previous = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old-", dir=folder.parent))
            os.rename(folder, previous / "old")
        else:
            folder.rmdir()
    os.rename(build, folder)
    if previous is not None:
        shutil.rmtree(previous, ignore_errors=True)
