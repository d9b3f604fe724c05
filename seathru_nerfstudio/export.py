"""``ns-export`` on a SeaThru run: the scene without the water.

nerfstudio's exporters read two things from a model (``nerfstudio/exporter``):

* ``model.get_rgba_image(outputs, name)``: the colour of each ray and its opacity. The point
  cloud (and the Poisson mesh made from it) keeps a ray's point where the opacity is above
  ``0.5``; the TSDF mesh and the textures of ``--texture-method nerf`` take the colour (the
  texture, and ``ns-render``'s ``rgba``, always ask for ``"rgb"``). :func:`get_rgba_image` gives
  the **clean** colour (the scene with the water removed) for ``"rgb"``, with the viewer's
  display transform (exposure, then sRGB for linear data: what MeshLab and Blender expect of
  8-bit vertex colours), and the object opacity ``accumulation`` as alpha, so open water (no
  object on the ray) exports no points. Other names: ``rgb_display`` is the colour in the water
  (camera renders only, e.g. ``ns-export tsdf``), any other colour output (``clean``,
  ``direct``, ``backscatter``) or its ``_display`` name gives that colour, display-transformed.
* ``outputs[depth_output_name]``: the TSDF integrates every pixel's depth. ``depth`` (nerfstudio's
  median depth) puts a ray that meets no object at the end of its samples, which the TSDF turns
  into a wall at the far bound. :data:`SURFACE_DEPTH` (``surface_depth``) is the depth where the
  ray meets an object (opacity above ``0.5``) and the largest float where it meets none, so the TSDF
  carves open water as free space: ``ns-export tsdf --depth-output-name surface_depth``.

Units: depths in scene units (as ``depth``), colours in ``[0, 1]``.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
from jaxtyping import Float
from torch import Tensor

from seathru_nerfstudio import viewer

OPACITY_THRESHOLD = 0.5
"""A ray meets a surface where its object opacity (``accumulation``) is above this: the opacity
above which nerfstudio's point cloud keeps a ray's point."""
SURFACE_DEPTH = "surface_depth"
"""The export depth output: :func:`surface_depth` of a camera render."""
EXPORT_OUTPUTS = (SURFACE_DEPTH,)
"""Whole-image outputs for the exporters, made from the object outputs (``depth``, ``accumulation``)."""
EXPORT_DEFAULT_COLOUR = "clean"
"""What the exporters' default colour name ``"rgb"`` gives (display-transformed)."""
PREMULTIPLIED = ("clean", "direct")
"""Colours that are sums over the object's weights, ``sum_i w_i c_i``: premultiplied by the opacity."""


def surface_depth(
    depth: Float[Tensor, "*batch 1"], accumulation: Float[Tensor, "*batch 1"], threshold: float = OPACITY_THRESHOLD
) -> Float[Tensor, "*batch 1"]:
    """``depth`` where ``accumulation > threshold`` (the ray meets a surface), else
    ``finfo(dtype).max``: farther than anything a TSDF holds, so it marks the whole ray free, and
    finite, so nerfstudio's ``origin + direction * depth`` and depth colour maps meet no ``0 * inf``."""
    no_surface = torch.full_like(depth, torch.finfo(depth.dtype).max)
    return torch.where(accumulation > threshold, depth, no_surface)


def export_output(name: str, outputs: Mapping[str, Tensor]) -> Tensor:
    """One of :data:`EXPORT_OUTPUTS` of a whole image's (or a batch of rays') outputs; reads only
    ``depth`` and ``accumulation`` (a lazily rendered image evaluates no medium for it)."""
    if name != SURFACE_DEPTH:
        raise KeyError(f"{name!r} is not an export output; they are {', '.join(EXPORT_OUTPUTS)}")
    return surface_depth(outputs["depth"], outputs["accumulation"])


def straight_colour(
    colour: Float[Tensor, "*batch 3"], accumulation: Float[Tensor, "*batch 1"], threshold: float = OPACITY_THRESHOLD
) -> Float[Tensor, "*batch 3"]:
    """A premultiplied object colour ``sum_i w_i c_i`` divided by ``max(accumulation, threshold)``:
    the surface's own colour wherever the ray is opaque enough to be exported, and, below, the
    colour over ``threshold`` (bounded by twice the premultiplied value, dark like the clean image
    of open water, never ``0 / 0``)."""
    return colour / accumulation.clamp_min(threshold)


def colour_source(output_name: str) -> str:
    """The linear colour output that ``output_name`` exports: ``"rgb"`` (the exporters' default)
    is :data:`EXPORT_DEFAULT_COLOUR`, ``"<colour>_display"`` and ``"<colour>"`` are ``<colour>``."""
    if output_name == "rgb":
        return EXPORT_DEFAULT_COLOUR
    name = output_name[: -len(viewer.DISPLAY_SUFFIX)] if output_name.endswith(viewer.DISPLAY_SUFFIX) else output_name
    if name not in viewer.COLOUR_OUTPUTS:
        raise ValueError(
            f"--rgb-output-name {output_name}: not a colour; use rgb (the clean colour, the default), "
            f"rgb_display (in the water) or one of {', '.join(viewer.COLOUR_OUTPUTS[1:])}"
        )
    return name


def get_rgba_image(model: Any, outputs: Mapping[str, Tensor], output_name: str = "rgb") -> Float[Tensor, "*batch 4"]:
    """``SeathruModel.get_rgba_image``: the colour named ``output_name`` (:func:`colour_source`),
    un-premultiplied for object colours (:func:`straight_colour`), display-transformed as the viewer
    shows it (``model.viewer_controls``), with the object opacity ``accumulation`` as alpha."""
    source = colour_source(output_name)
    accumulation = outputs["accumulation"]
    colour = outputs[source]
    if source in PREMULTIPLIED:
        colour = straight_colour(colour, accumulation)
    shown = model.viewer_controls.display_output(source + viewer.DISPLAY_SUFFIX, {source: colour})
    return torch.cat([shown, accumulation.to(shown.dtype)], dim=-1)
