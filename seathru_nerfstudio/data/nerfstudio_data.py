"""nerfstudio's own ``nerfstudio-data`` parser, telling the model its scale.

The model reports the medium per metre (world unit), not per scene unit, and takes an
oracle medium in 1/m. Both need the dataparser scale (scene units per world unit), which
nerfstudio keeps in ``DataparserOutputs.dataparser_scale`` but does not hand to the model;
this parser copies it into ``metadata["dataparser_scale"]``, which the model receives.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig

SCALE_KEY = "dataparser_scale"
"""Metadata key: scene units per world unit (a float)."""


@dataclass
class SeathruNerfstudioDataParserConfig(NerfstudioDataParserConfig):
    """``nerfstudio-data`` (transforms.json), with the scale in the model's metadata."""

    _target: Type = field(default_factory=lambda: SeathruNerfstudio)


class SeathruNerfstudio(Nerfstudio):
    """nerfstudio's parser; ``metadata["dataparser_scale"]`` added."""

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        outputs = super()._generate_dataparser_outputs(split, **kwargs)
        outputs.metadata[SCALE_KEY] = float(outputs.dataparser_scale)
        return outputs
