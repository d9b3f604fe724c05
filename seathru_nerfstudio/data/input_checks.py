"""The checks a dataset passes once, when it is loaded, so that training never starts on bad input.

Each failure is an :class:`~seathru_nerfstudio.input_errors.InputError` whose one line names the
file (and the frame) and says what to do; ``ns-train`` stops with it within seconds instead of
hanging in a data-loading worker, training on NaNs, or failing deep inside nerfstudio.

* ``transforms.json`` (:func:`load_transforms`): valid JSON, at least one frame, every frame with
  a ``file_path`` and a finite 4×4 (or 3×4) ``transform_matrix``, finite camera numbers, the
  files it names (image, ``depth_file_path``, ``mask_path``) present, and the
  split lists naming frames; a field given for some frames must be given for all.
* Images (:func:`check_images`): readable, of the size the camera says (nerfstudio stacks them:
  one of another size kills its data-loading worker), no NaN/inf pixel, not all black, not all
  white. Each file is read once per process (a cache keyed on path, size and modification time:
  nerfstudio asks for the same split more than once). Several files are read at once: decoding
  releases the GIL.
"""

from __future__ import annotations

import json
import math
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from seathru_nerfstudio.data.linear_images import read_linear_image
from seathru_nerfstudio.input_errors import InputError

FRAME_FILE_FIELDS = ("file_path", "depth_file_path", "mask_path")
"""Frame fields that name a file relative to ``transforms.json``; all are checked for existence."""
CAMERA_FIELDS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2")
"""Numbers a ``transforms.json`` gives for the camera, at the top or per frame."""


class DatasetError(InputError):
    """The dataset (``transforms.json`` or a file it names) is not usable; the message says which and why."""


def _where(path: Path, index: int, frame: Dict[str, Any]) -> str:
    name = frame.get("file_path") if isinstance(frame, dict) else None
    return f"{path}: frame {index}" + (f" ({name})" if name else "")


def load_transforms(path: Path) -> Dict[str, Any]:
    """``transforms.json`` at ``path`` (a file, or a folder holding it), parsed and checked; raises
    :class:`DatasetError` naming the file, the frame and the field."""
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    if not path.is_file():
        hint = "" if path.parent.is_dir() else f" ({path.parent} does not exist)"
        raise DatasetError(f"{path}: no such file{hint}. Point --data at a folder made by seathru-process-data or seathru-synth")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as error:
        raise DatasetError(f"{path}: not a text file ({error.reason})") from None
    except json.JSONDecodeError as error:
        raise DatasetError(
            f"{path}: not valid JSON at line {error.lineno} column {error.colno}: {error.msg}. Fix the file there"
        ) from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise DatasetError(f'{path}: expected an object with a "frames" list')
    frames = meta["frames"]
    if not frames:
        raise DatasetError(f"{path} has no frames: nothing to train on. Add frames, or run seathru-process-data again")
    _check_numbers(path, "the top level", meta)
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise DatasetError(f'{path}: frame {index} has no "file_path"')
        where = _where(path, index, frame)
        _check_pose(where, frame.get("transform_matrix"))
        _check_numbers(path, f"frame {index} ({frame['file_path']})", frame)
    for field in FRAME_FILE_FIELDS[1:]:
        given = [i for i, frame in enumerate(frames) if field in frame]
        if given and len(given) < len(frames):
            missing = next(i for i in range(len(frames)) if field not in frames[i])
            raise DatasetError(
                f"{_where(path, missing, frames[missing])} has no {field!r}, but {len(given)} of the {len(frames)} "
                "frames have one: give it for every frame or for none"
            )
    names = {os.path.normpath(frame["file_path"]) for frame in frames}
    for split in ("train", "val", "test"):
        listed = meta.get(f"{split}_filenames")
        if listed is None:
            continue
        unknown = [name for name in listed if os.path.normpath(str(name)) not in names]
        if unknown:
            raise DatasetError(
                f"{path}: {split}_filenames lists {len(unknown)} image(s) that no frame has, e.g. {unknown[0]}. "
                "Remove them from the list or add their frames"
            )
    for index, frame in enumerate(frames):
        for field in FRAME_FILE_FIELDS:
            if field in frame and not (path.parent / frame[field]).is_file():
                raise DatasetError(
                    f"{_where(path, index, frame)}: {field} {frame[field]} does not exist "
                    f"({path.parent / frame[field]}). Restore the file or remove the frame"
                )
    return meta


def _check_pose(where: str, matrix: Any) -> None:
    try:
        pose = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        pose = None
    if pose is None or pose.shape not in ((4, 4), (3, 4)):
        shape = "missing" if matrix is None else f"of shape {getattr(pose, 'shape', '?')}"
        raise DatasetError(f"{where}: transform_matrix is {shape}; expected a 4×4 camera-to-world matrix")
    if not np.all(np.isfinite(pose)):
        row, column = np.argwhere(~np.isfinite(pose))[0]
        raise DatasetError(
            f"{where}: transform_matrix[{row}][{column}] is {pose[row, column]} (a pose must be finite). "
            "Fix this pose or remove the frame"
        )


def _check_numbers(path: Path, where: str, fields: Dict[str, Any]) -> None:
    for name in CAMERA_FIELDS:
        if name not in fields:
            continue
        value = fields[name]
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if ok and name in ("fl_x", "fl_y", "w", "h"):
            ok = value > 0
        if not ok:
            raise DatasetError(f"{path}: {where}: {name} is {value!r}; expected a finite number{' > 0' * (name in ('fl_x', 'fl_y', 'w', 'h'))}")


# ------------------------------------------------------------------------------------ images
_checked: Dict[Tuple[str, int, int, int, int], Optional[str]] = {}
"""(path, size, mtime, height, width) -> the problem found (None: fine); see the module docstring."""


def image_problem(path: Path, height: int, width: int) -> Optional[str]:
    """What is wrong with the image at ``path`` for a camera of ``height`` × ``width`` px
    (``None``: nothing): its one-line message names the file."""
    try:
        stat = os.stat(path)
    except OSError:
        return f"{path}: no such image file. Restore it or remove its frame"
    key = (str(path), stat.st_size, stat.st_mtime_ns, int(height), int(width))
    if key not in _checked:
        _checked[key] = _image_problem(Path(path), int(height), int(width))
    return _checked[key]


def _image_problem(path: Path, height: int, width: int) -> Optional[str]:
    try:
        image = read_linear_image(path)[..., :3]
    except InputError as error:
        return str(error)
    if image.shape[:2] != (height, width):
        return (
            f"{path} is {image.shape[1]}×{image.shape[0]} px, but its camera is {width}×{height} "
            "(w, h in transforms.json): every image must have its camera's size. Resize or replace the image"
        )
    finite = np.isfinite(image)
    if not finite.all():
        row, column = np.argwhere(~finite.all(axis=-1))[0]
        count = int((~finite.all(axis=-1)).sum())
        return f"{path} has {count} NaN or inf pixel(s) (the first at row {row}, column {column}). Fix or remove the image"
    if image.max() <= 0.0:
        return f"{path} is all black (every pixel 0): a lens cap or a failed exposure? Remove its frame"
    if image.min() >= 1.0:
        return f"{path} is all white (every pixel saturated): overexposed. Remove its frame"
    return None


def check_images(paths: Sequence[Path], heights: Sequence[int], widths: Sequence[int], threads: int = 4) -> None:
    """Raise :class:`DatasetError` for the first image (in ``paths`` order) with a problem
    (:func:`image_problem`), saying how many more have one."""
    with ThreadPoolExecutor(max_workers=max(1, min(threads, os.cpu_count() or 1))) as pool:
        problems: List[Optional[str]] = list(pool.map(image_problem, paths, heights, widths))
    found = [problem for problem in problems if problem is not None]
    if found:
        more = f" ({len(found) - 1} more image(s) have a problem too)" if len(found) > 1 else ""
        raise DatasetError(found[0] + more)
