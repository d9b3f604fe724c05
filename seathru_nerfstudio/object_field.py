"""nerfacto's object field fitted to an underwater capture: Lambertian colour in a medium, the
scene contraction at the scene, and rays bounded by the SfM near and far bounds.

* **Lambertian colour in a medium** (:class:`FixedDirectionEncoding`), as the official SeaThru-NeRF:
  a view-dependent look must come from the medium, and multi-view consistency pins the colour. In
  clear air (``none``) no medium could take it, and the colour is nerfacto's, view-dependent
  (path-traced clear layouts 7, 8 and 9, seed 42: 33.96, 35.17 and 34.57 dB in held-out PSNR against
  33.67, 35.07 and 34.04 Lambertian; matched nerfacto 33.84, 34.42 and 34.91; over six paired runs,
  seed 7 and the clear demo included, +0.16 dB on average, −0.12 to +0.53; docs/history.md).
* **Contraction at the scene** (:class:`~seathru_nerfstudio.contraction.ContractionBeyond`): a
  forward-facing rig sees out of nerfstudio's unit cube, so its whole scene would lie in the
  contracted shell; with a medium the contraction starts at the extent the cameras see up to the
  far bound. Clear air (``none``) keeps nerfacto's, so that its hash tables hold the near surfaces
  that fill a clear view (path-traced clear air: 34.06 / 34.47 dB against nerfacto's 34.12 / 34.05,
  30.95 at the scene's extent). :meth:`SeathruModel.fit_object_field_to_medium_model` sets both.
* **Bounds** (:func:`scene_collider`): rays start at 0.9 of the SfM near bound (no dark screen in
  front of the lens) and end at ``far_bound_margin`` times the far bound (an unbounded field starts
  as an opaque wall behind the open water); the renderer adds the water outside in closed form.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

import torch
from torch import nn

from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.model_components.scene_colliders import NearFarCollider

from seathru_nerfstudio.contraction import ContractionBeyond
from seathru_nerfstudio.metadata_keys import EXTENT_KEY


class FixedDirectionEncoding(nn.Module):
    """An encoding that, while ``fixed``, encodes one fixed direction: a colour head fed by it is
    view-independent (Lambertian), with nerfacto's field left as it is; not ``fixed``, the wrapped
    encoding of the ray's own direction (nerfacto's view-dependent colour)."""

    def __init__(self, encoding: nn.Module, fixed: bool = True) -> None:
        super().__init__()
        self.encoding = encoding
        self.fixed = fixed

    def get_out_dim(self) -> int:
        return self.encoding.get_out_dim()

    def forward(self, directions: torch.Tensor) -> torch.Tensor:
        if not self.fixed:
            return self.encoding(directions)
        fixed = torch.zeros_like(directions[:1])
        fixed[..., 2] = 1.0
        return self.encoding(fixed).expand(directions.shape[0], -1)


def scene_contraction_radius(metadata: Mapping[str, Any]) -> float:
    """Where a medium model's contraction starts: the extent the cameras see up to the SfM far bound
    (scene units; at least nerfacto's 1), or 1 without it."""
    return max(1.0, float(metadata[EXTENT_KEY])) if EXTENT_KEY in metadata else 1.0


def set_contraction(field: nn.Module, proposal_networks: nn.ModuleList, radius: float) -> float:
    """Give the object field and the proposal networks one contraction that starts at ``radius``
    (scene units): nerfstudio's own :class:`SceneContraction` at 1, :class:`ContractionBeyond`
    beyond. Returns ``radius``."""
    contraction = SceneContraction(order=float("inf")) if radius == 1.0 else ContractionBeyond(radius)
    field.spatial_distortion = contraction
    for network in proposal_networks:
        network.spatial_distortion = contraction
    return radius


def scene_collider(metadata: Mapping[str, Any], far_plane: float, far_bound_margin: float) -> Optional[NearFarCollider]:
    """A collider on the scene's own bounds (``near_plane``, ``far_plane`` of the dataparser's
    metadata, scene units), or ``None`` without them (nerfacto's collider stays)."""
    if "near_plane" not in metadata:
        return None
    far = far_plane
    if far_bound_margin > 0 and "far_plane" in metadata:
        far = far_bound_margin * float(metadata["far_plane"])
    return NearFarCollider(near_plane=0.9 * float(metadata["near_plane"]), far_plane=far)
