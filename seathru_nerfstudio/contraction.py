"""Where the object field's scene contraction starts: at the scene, not at the cameras.

nerfacto's hash grids read positions through mip-NeRF 360's contraction (L∞): the cube
``|x|∞ ≤ 1`` (scene units) maps linearly onto half the grid's extent, everything beyond into the
shell ``1 < |x|∞ < 2``, where the metric resolution falls as ``1/|x|²``. nerfstudio scales the poses
so that the cameras fill that cube, which suits cameras around an object. A forward-facing
underwater rig looks *out* of its cube: on the demos every surface sits 3 to 20 scene units away,
and turbid's far wall (8 m) gets grid cells about 0.5 m deep, so its surfaces came out as 10%-thick
ramps whose median sits 4% behind the truth (b2f1003, 2026-11-26; docs/history.md).

:class:`ContractionBeyond` contracts ``x / radius`` instead, with ``radius`` the extent of what
the cameras can see up to the scene's far bound
(:func:`seathru_nerfstudio.data.nerfstudio_data.frustum_extent`): the scene is resolved
linearly, and only the space behind it is contracted. The model has used it since 88414fa
(2026-11-26): on turbid it fixes the far surfaces (far-third depth error 0.085 -> 0.011), and with
the veiling light learned from open rays the open water stays empty (docs/history.md).
"""

from __future__ import annotations

import math
from typing import Union

from jaxtyping import Float
from torch import Tensor

from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.utils.math import Gaussians


class ContractionBeyond(SceneContraction):
    """nerfstudio's L∞ :class:`SceneContraction` of ``x / radius``: linear (``x / radius``) where
    ``|x|∞ ≤ radius``, contracted beyond, into ``|f(x)|∞ < 2`` as nerfacto's grids expect.
    ``radius`` in scene units; 1 is nerfstudio's contraction exactly."""

    def __init__(self, radius: float) -> None:
        if not (math.isfinite(radius) and radius > 0):
            raise ValueError(f"the contraction radius must be finite and positive, got {radius}")
        super().__init__(order=float("inf"))
        self.radius = float(radius)

    def forward(
        self, positions: Union[Float[Tensor, "*bs 3"], Gaussians]
    ) -> Union[Float[Tensor, "*bs 3"], Gaussians]:
        if isinstance(positions, Gaussians):
            scaled = Gaussians(mean=positions.mean / self.radius, cov=positions.cov / self.radius**2)
            return super().forward(scaled)
        return super().forward(positions / self.radius)
