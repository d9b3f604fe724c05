"""A contact sheet of rendered scenes: per scene one held-out view's in-medium image, its J and
its medium-free render, side by side (display gamma 1/2.2, the same scale for the three).

Usage::

    python -m seathru_nerfstudio.data.pathtrace.contact OUT.png SCENE [SCENE ...]
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from seathru_nerfstudio.data.linear_images import read_linear_image


def contact_sheet(scenes: Sequence[Path], out: Path, view: str = "frame_00008.png", scale: float = 0.6) -> None:
    """Write ``out`` (8-bit PNG): one row per scene folder, columns I | J | medium-free, each
    tile area-resized by ``scale`` (the noise makes full-size sheets large files)."""
    rows = []
    for scene in scenes:
        tiles = [read_linear_image(Path(scene) / sub / view, scale_factor=scale)[..., :3] for sub in ("images", "ground_truth/clean", "ground_truth/dry")]
        rows.append(np.concatenate([np.pad(t, ((2, 2), (2, 2), (0, 0)), constant_values=1.0) for t in tiles], axis=1))
    sheet = np.concatenate(rows, axis=0)
    display = np.round(np.clip(sheet, 0.0, 1.0) ** (1.0 / 2.2) * 255.0).astype(np.uint8)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), display[..., ::-1]):
        raise OSError(f"{out}: could not write image")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit("usage: python -m seathru_nerfstudio.data.pathtrace.contact OUT.png SCENE [SCENE ...]")
    contact_sheet([Path(p) for p in sys.argv[2:]], Path(sys.argv[1]))
