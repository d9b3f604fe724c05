"""nerfstudio's own ``nerfstudio-data`` parser, telling the model its scale and near bound.

* The model reports the medium per metre (world unit), not per scene unit, and takes an
  oracle medium in 1/m. Both need the dataparser scale (scene units per world unit), which
  nerfstudio keeps in ``DataparserOutputs.dataparser_scale`` but does not hand to the model;
  this parser copies it into ``metadata["dataparser_scale"]``, which the model receives.
* When the frames have sparse SfM depths (``depth_file_path``), the nearest of them bounds
  where objects can be, as LLFF's ``poses_bounds`` do for ``seathru-data``:
  ``metadata["near_plane"]`` (scene units). In water this matters: an object field allowed
  right in front of the lens can explain the whole image as a dark screen veiled by
  backscatter, which the renderer's closed-form water in front of the near plane rules out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Type

import numpy as np

from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from nerfstudio.data.utils.data_utils import get_depth_image_from_path

SCALE_KEY = "dataparser_scale"
"""Metadata key: scene units per world unit (a float)."""
NEAR_PERCENTILE = 0.1
"""Per image, the near bound is this percentile of its SfM depths (LLFF's choice), so that a
stray point does not set it."""


@dataclass
class SeathruNerfstudioDataParserConfig(NerfstudioDataParserConfig):
    """``nerfstudio-data`` (transforms.json), with the scale in the model's metadata."""

    _target: Type = field(default_factory=lambda: SeathruNerfstudio)


class SeathruNerfstudio(Nerfstudio):
    """nerfstudio's parser; ``metadata["dataparser_scale"]`` added."""

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        outputs = super()._generate_dataparser_outputs(split, **kwargs)
        scale = float(outputs.dataparser_scale)
        outputs.metadata[SCALE_KEY] = scale
        depth_files = outputs.metadata.get("depth_filenames")
        if depth_files:
            unit = float(outputs.metadata["depth_unit_scale_factor"])
            near = sfm_near_bound(depth_files, outputs.cameras.height, outputs.cameras.width)
            if near is not None:
                outputs.metadata["near_plane"] = near * unit * scale
        return outputs


def sfm_near_bound(depth_files, heights, widths) -> float | None:
    """Smallest per-image ``NEAR_PERCENTILE`` of the sparse depths (file units; z-depth, which
    is never more than the range, so the bound is conservative); ``None`` without any point."""
    nears = []
    for path, height, width in zip(depth_files, heights.flatten().tolist(), widths.flatten().tolist()):
        depth = get_depth_image_from_path(Path(path), int(height), int(width), scale_factor=1.0).numpy()
        known = depth[depth > 0]
        if known.size:
            nears.append(float(np.percentile(known, NEAR_PERCENTILE)))
    return min(nears) if nears else None
