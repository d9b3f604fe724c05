"""Per-frame ground truth, declared by the scene the way nerfstudio declares depth.

A frame of ``transforms.json`` may name, beside nerfstudio's ``file_path`` and
``depth_file_path`` (the sparse SfM depth the depth loss uses), its ground truth, paths
relative to the scene folder (``seathru-synth`` writes both for every frame):

* ``gt_depth_file_path``: the true range, ``.npy`` float32 ``H x W`` in world units (metres)
  from the camera centre along the pixel-centre ray, ``inf`` where the pixel sees open water;
* ``gt_clean_file_path``: the clean image (no medium), a linear (16-bit) image.

The ``nerfstudio-data`` parser of this package puts them in ``DataparserOutputs.metadata`` as
lists of paths that follow ``image_filenames`` (keys below), and ``LinearImageDataset`` loads
them from there into the batch keys ``gt_depth`` and ``gt_clean``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Sequence

GT_DEPTH_FILENAMES = "gt_depth_filenames"
GT_CLEAN_FILENAMES = "gt_clean_filenames"
FRAME_FIELDS: Dict[str, str] = {GT_DEPTH_FILENAMES: "gt_depth_file_path", GT_CLEAN_FILENAMES: "gt_clean_file_path"}
"""Metadata key -> the ``transforms.json`` frame field it is read from."""

LEGACY_FOLDER = "ground_truth"
"""Where ``seathru-synth`` scenes written before the frame fields existed keep their ground
truth: ``ground_truth/clean/<image name>`` and ``ground_truth/depth/<image stem>.npy``."""


def legacy_paths(scene: Path, image_filenames: Sequence[Path]) -> Dict[str, List[Path]]:
    """The ground truth of an older ``seathru-synth`` scene, found by its fixed layout: the
    metadata entries whose files exist for every image (none for other datasets)."""
    root = scene / LEGACY_FOLDER
    candidates = {
        GT_CLEAN_FILENAMES: [root / "clean" / Path(p).name for p in image_filenames],
        GT_DEPTH_FILENAMES: [(root / "depth" / Path(p).name).with_suffix(".npy") for p in image_filenames],
    }
    return {key: paths for key, paths in candidates.items() if paths and all(p.is_file() for p in paths)}
