"""Whole-image renders outside training (evaluation, the viewer, ``ns-render``), computed lazily.

A camera render returns :class:`~seathru_nerfstudio.lazy_outputs.LazyOutputs`: the display
outputs of :mod:`seathru_nerfstudio.viewer` first (nerfstudio's viewer opens on the first
output), then the linear ones, each computed when it is first read. A view of ``clean`` or of
``depth`` never evaluates the medium, a medium map never evaluates the object field, and ``rgb``
brings the object outputs along (one pass over the field) but not the medium maps.
"""

from __future__ import annotations

from typing import Any, Dict, Iterator, List, Tuple

import torch

from nerfstudio.cameras.rays import RayBundle

from seathru_nerfstudio import export, viewer
from seathru_nerfstudio.lazy_outputs import LazyOutputs

WATER_OUTPUTS = ("rgb", "direct", "backscatter")
"""Outputs that need the object field and the medium."""
OBJECT_OUTPUTS = ("clean", "depth", "expected_depth", "accumulation")
"""Outputs of the object field alone (with the proposal depths ``prop_depth_<i>``)."""
MEDIUM_OUTPUTS = ("medium_rgb", "medium_attenuation", "medium_backscatter")
"""Per-ray medium maps: the medium alone, without the object field."""


def proposal_depth_names(model: Any) -> Tuple[str, ...]:
    return tuple(f"prop_depth_{i}" for i in range(model.config.num_proposal_iterations))


def lazy_camera_outputs(model: Any, camera_ray_bundle: RayBundle) -> LazyOutputs:
    """Every output of a camera's image (``H x W x C``), each rendered when first read."""
    names = viewer.DISPLAY_OUTPUTS + WATER_OUTPUTS + OBJECT_OUTPUTS + MEDIUM_OUTPUTS + proposal_depth_names(model)
    names += export.EXPORT_OUTPUTS  # for ns-export (surface_depth), from the object outputs

    @torch.no_grad()  # read later, outside the caller's no_grad (ns-render reads with grad on)
    def compute(name: str, outputs) -> Dict[str, torch.Tensor]:
        if name in viewer.DISPLAY_OUTPUTS:
            return {name: model.viewer_controls.display_output(name, outputs)}
        if name in MEDIUM_OUTPUTS:
            return render_medium_maps(model, camera_ray_bundle)
        if name in export.EXPORT_OUTPUTS:
            return {name: export.export_output(name, outputs)}
        return render_image(model, camera_ray_bundle, with_medium=name in WATER_OUTPUTS)

    return LazyOutputs(names, compute)


def render_image(model: Any, camera_ray_bundle: RayBundle, with_medium: bool) -> Dict[str, torch.Tensor]:
    """nerfstudio's chunked whole-image render (``eval_num_rays_per_chunk`` rays at a time) of the
    water and object outputs, or (``with_medium=False``) of the object outputs only."""
    keep = (WATER_OUTPUTS if with_medium else ()) + OBJECT_OUTPUTS + proposal_depth_names(model)
    chunks: Dict[str, List[torch.Tensor]] = {name: [] for name in keep}
    for bundle in _chunks(model, camera_ray_bundle):
        bundle = model.collider(bundle) if model.collider is not None else bundle
        outputs = model.get_outputs(bundle, with_medium=with_medium)
        for name in keep:
            chunks[name].append(outputs[name].to(camera_ray_bundle.origins.device))
    return _images(camera_ray_bundle, chunks)


def render_medium_maps(model: Any, camera_ray_bundle: RayBundle) -> Dict[str, torch.Tensor]:
    """The per-ray medium maps, from the ray directions alone (no object field)."""
    chunks: Dict[str, List[torch.Tensor]] = {name: [] for name in MEDIUM_OUTPUTS}
    for bundle in _chunks(model, camera_ray_bundle):
        medium = model.medium(bundle.directions.to(model.device))
        for name, value in zip(MEDIUM_OUTPUTS, (medium.rgb, medium.sigma_attn, medium.sigma_bs)):
            chunks[name].append(value.to(camera_ray_bundle.origins.device))
    return _images(camera_ray_bundle, chunks)


def _chunks(model: Any, camera_ray_bundle: RayBundle) -> Iterator[RayBundle]:
    """An image's rays in row-major chunks of ``eval_num_rays_per_chunk``, on the model's device."""
    step = model.config.eval_num_rays_per_chunk
    for start in range(0, len(camera_ray_bundle), step):
        yield camera_ray_bundle.get_row_major_sliced_ray_bundle(start, start + step).to(model.device)


def _images(camera_ray_bundle: RayBundle, chunks: Dict[str, List[torch.Tensor]]) -> Dict[str, torch.Tensor]:
    height, width = camera_ray_bundle.origins.shape[:2]
    return {name: torch.cat(values).view(height, width, -1) for name, values in chunks.items()}
