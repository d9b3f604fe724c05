"""Writing what our data commands produce: 16-bit linear PNGs, and output folders that
appear whole or not at all.

* Images: linear values in [0, 1] are stored as ``round(value * 65535)`` in a 16-bit PNG, RGB
  channel order (OpenCV's BGR is swapped here), no gamma, no sRGB chunk.
* Folders: :func:`atomic_output_folder` builds everything in a hidden sibling
  (``.<name>.partial-*``) and renames it into place when the build succeeds; an interrupted or
  failed build leaves no half-written folder, and the folder it replaces (``--overwrite``)
  stays untouched until the last moment. The folder and files get the modes that the user's
  umask gives a plain ``mkdir`` / ``open`` (0755 / 0644 under umask 022), not the 0700 / 0600 of
  Python's ``tempfile``.
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

from seathru_nerfstudio.input_errors import InputError


class OutputFolderError(InputError):
    """The output folder cannot be written (it is a file, it holds files and may not be replaced, or
    its parent is not writable)."""


def current_umask() -> int:
    """The process's umask (read by setting it and putting it back: POSIX has no plain getter)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _as_if_created(path: Path, mode: int) -> None:
    """Give ``path`` (made by ``tempfile``, mode 0700/0600) the mode a plain ``mkdir``/``open``
    would have given it under the current umask (``mode`` 0o777 or 0o666 before the mask)."""
    os.chmod(path, mode & ~current_umask())


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


@contextlib.contextmanager
def atomic_file(path: Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (ending in ``suffix``, for writers that read the
    format from the name) to write to; when the block ends without an error it is renamed over
    ``path`` with the mode a plain ``open`` would give. On an error it is deleted and ``path`` is
    untouched."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, name = tempfile.mkstemp(prefix=f".{path.name}.partial-", suffix=suffix, dir=path.parent)
    os.close(handle)
    temporary = Path(name)
    try:
        yield temporary
        _as_if_created(temporary, 0o666)
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file beside ``path``, then rename it over ``path``."""
    with atomic_file(path) as temporary:
        temporary.write_text(text, encoding="utf-8")


def check_output_folder(folder: Path, overwrite: bool) -> None:
    """Raise :class:`OutputFolderError` unless ``folder`` is missing, empty, or may be replaced."""
    if folder.exists() and not folder.is_dir():
        raise OutputFolderError(f"--output-dir {folder} exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise OutputFolderError(
            f"{folder} already holds files. Pass --overwrite to replace it, or choose another --output-dir"
        )


def check_writable_parent(folder: Path) -> None:
    """Raise :class:`OutputFolderError` unless the nearest existing parent of ``folder`` accepts a
    new entry: tried with a real folder, made and removed at once (permission bits tell neither a
    read-only file system nor what root may do)."""
    folder = Path(folder).absolute()
    parent = next(p for p in folder.parents if p.exists())
    try:
        Path(tempfile.mkdtemp(prefix=f".{folder.name}.probe-", dir=parent)).rmdir()
    except OSError as error:
        raise OutputFolderError(
            f"cannot create --output-dir {folder}: {parent} is not writable ({error.strerror}). "
            "Choose a folder you can write to"
        ) from None


@contextlib.contextmanager
def atomic_output_folder(folder: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield an empty hidden sibling of ``folder`` to build in; when the block ends without an
    error, it becomes ``folder`` (replacing what was there, which needs ``overwrite`` unless the
    folder is missing or empty). On an error the build is deleted and ``folder`` is untouched.

    Raises :class:`OutputFolderError` before the block runs (``folder`` may not be replaced, or its
    parent is not writable), and again before the swap (the folder may have been filled meanwhile).
    """
    folder = Path(folder)
    check_output_folder(folder, overwrite)
    check_writable_parent(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    build = Path(tempfile.mkdtemp(prefix=f".{folder.name}.partial-", dir=folder.parent))
    _as_if_created(build, 0o777)
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
