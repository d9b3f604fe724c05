"""Water on, water off: SeaThru-NeRF in nerfstudio's live viewer and in ``ns-render``.

How a pixel reaches the screen:

* **Outputs are linear for every caller.** ``rgb``, ``clean``, ``direct``, ``backscatter`` and
  ``medium_rgb`` are linear radiance, the ``medium_*`` densities are per scene unit, whoever
  asks: training, ``ns-eval``, the benchmark, the viewer, ``ns-render``, scripts.
* **Display versions are separate outputs, by name.** Every camera render outside training
  (``SeathruModel.get_outputs_for_camera_ray_bundle``) also returns :data:`DISPLAY_OUTPUTS`,
  made by :meth:`SeathruViewerControls.display_outputs` from the controls' current values:
  ``<colour>_display`` (exposure ``2**stops``, then sRGB encoding, on by default for linear
  data; ``rgb_display`` is the clean image when *Water* is off), ``<density>_display`` (the
  densities over their largest value in the image) and ``water_split`` (left half in the water,
  right half clean). They come first in the outputs, so nerfstudio's viewer, which selects the
  first output, opens on ``rgb_display``; ``ns-render --rendered-output-names clean_display``
  makes a video to watch, ``--rendered-output-names clean`` one of the linear values.
* **The water controls change the medium itself**: the density scale and the veiling-light
  colour are read from the ``ViewerElement`` s by ``SeathruModel.get_outputs`` whenever the
  model is not training and its plain flag ``medium_controls_enabled`` is on (so the viewer
  re-simulates other water, linear outputs included). At their defaults they change nothing.
  :class:`~seathru_nerfstudio.pipeline.SeathruPipeline` turns the flag off while it evaluates:
  ``ns-eval`` and the evaluations while training measure the trained medium. A flag on the
  model suffices because nerfstudio's ``train_lock`` (held by the viewer's render threads,
  by training and by evaluation; ``ns-viewer`` shares one lock between its render threads)
  never lets a viewer render and an evaluation run at the same time.

Why names rather than a display mode: the viewer, ``ns-render`` and ``ns-eval`` all call
``model.get_outputs_for_camera`` in the same way, and nothing public tells them apart for
``ns-render``; a named output is what every one of them can ask for.

Nothing here is a parameter or a buffer (the state dict is unchanged), and nothing applies
while the model trains.
"""

from __future__ import annotations

from typing import Dict, Mapping, Optional, Tuple

import torch
from torch import Tensor, nn

from nerfstudio.viewer.viewer_elements import ViewerCheckbox, ViewerRGB, ViewerSlider

from seathru_nerfstudio.colour import linear_to_srgb, srgb_to_linear
from seathru_nerfstudio.medium_field import MediumOutputs

COLOUR_OUTPUTS = ("rgb", "clean", "direct", "backscatter", "medium_rgb")
"""Linear colours: their display versions get the exposure and the sRGB encoding."""
DENSITY_OUTPUTS = ("medium_attenuation", "medium_backscatter")
"""Densities per scene unit: their display versions are normalised by the image's maximum."""
DISPLAY_SUFFIX = "_display"
SPLIT_OUTPUT = "water_split"
"""Display output: left half ``rgb`` (in the medium), right half ``clean``."""
DISPLAY_OUTPUTS = tuple(name + DISPLAY_SUFFIX for name in COLOUR_OUTPUTS + DENSITY_OUTPUTS) + (SPLIT_OUTPUT,)
"""Every display output, in the order a camera render returns them (before the linear ones)."""

DEFAULT_VEIL_SRGB = (30, 110, 160)
"""Initial colour of the veiling-light picker (8-bit sRGB, a deep blue-green)."""
SPLIT_LINE = 0.9
"""Grey level of the one-pixel line between the two halves of ``water_split``."""


def tone(image: Tensor, exposure: float, srgb: bool) -> Tensor:
    """Exposure ``2**exposure``, then sRGB encoding (or a clamp): a linear colour ready to show."""
    image = image * (2.0**exposure)
    return linear_to_srgb(image) if srgb else image.clamp(0.0, 1.0)


def water_split(rgb: Tensor, clean: Tensor) -> Tensor:
    """Left half ``rgb`` (in the medium), right half ``clean``, a light line between; ``[H, W, 3]``."""
    half = rgb.shape[1] // 2
    split = torch.cat([rgb[:, :half], clean[:, half:]], dim=1)
    if split.shape[1] > 2:
        split[:, half] = SPLIT_LINE
    return split


def display_sources(name: str, water: bool) -> Tuple[str, ...]:
    """The linear outputs that the display output ``name`` is made from."""
    if name == SPLIT_OUTPUT:
        return ("rgb", "clean")
    if name == "rgb" + DISPLAY_SUFFIX and not water:
        return ("clean",)
    if name in DISPLAY_OUTPUTS:
        return (name[: -len(DISPLAY_SUFFIX)],)
    raise KeyError(f"{name!r} is not a display output; they are {', '.join(DISPLAY_OUTPUTS)}")


def display_output(name: str, outputs: Mapping[str, Tensor], water: bool, exposure: float, srgb: bool) -> Tensor:
    """One display output (:data:`DISPLAY_OUTPUTS`) of a whole image's linear outputs
    (``[H, W, C]`` each); reads only its :func:`display_sources`, so that a lazily rendered
    image computes nothing else."""
    sources = [outputs[source] for source in display_sources(name, water)]
    if name == SPLIT_OUTPUT:
        return water_split(*(tone(source, exposure, srgb) for source in sources))
    if name[: -len(DISPLAY_SUFFIX)] in DENSITY_OUTPUTS:
        return (sources[0] / sources[0].max().clamp_min(1e-12)).clamp(0.0, 1.0)
    return tone(sources[0], exposure, srgb)


def display_outputs(outputs: Dict[str, Tensor], water: bool, exposure: float, srgb: bool) -> Dict[str, Tensor]:
    """Every display output (:data:`DISPLAY_OUTPUTS`) of a whole image's linear outputs
    (``[H, W, C]`` each); those whose sources are missing are skipped."""
    return {
        name: display_output(name, outputs, water, exposure, srgb)
        for name in DISPLAY_OUTPUTS
        if all(source in outputs for source in display_sources(name, water))
    }


def override_medium(
    medium: MediumOutputs, density_scale: float, veil_rgb: Optional[Tuple[float, float, float]]
) -> MediumOutputs:
    """The medium with its densities scaled and, if given, its veiling light replaced (linear RGB).
    Returns ``medium`` itself when that changes nothing."""
    if density_scale == 1.0 and veil_rgb is None:
        return medium
    rgb = medium.rgb
    if veil_rgb is not None:
        rgb = torch.tensor(veil_rgb, dtype=rgb.dtype, device=rgb.device).expand_as(rgb)
    return MediumOutputs(rgb=rgb, sigma_attn=medium.sigma_attn * density_scale, sigma_bs=medium.sigma_bs * density_scale)


class SeathruViewerControls(nn.Module):
    """The viewer controls, as nerfstudio ``ViewerElement`` attributes.

    nerfstudio's viewer finds them by walking the pipeline's attributes and ``nn.Module``
    children (``parse_object``), hence an ``nn.Module``; it holds no parameters or buffers,
    so checkpoints do not change. The attribute names set the order in the GUI (nerfstudio
    sorts them). Without a GUI (``ns-render``, tests) each element's value is its default;
    setting ``element.value`` then changes it.
    """

    def __init__(self, linear_data: bool) -> None:
        super().__init__()
        self.linear_data = linear_data
        self.c1_water = ViewerCheckbox(
            "Water", True, hint="Off: 'rgb_display' shows the scene without the water (the clean image)."
        )
        self.c2_density = ViewerSlider(
            "Water density",
            1.0,
            0.0,
            3.0,
            0.05,
            hint="Multiplies the medium's attenuation and backscatter densities (0 = clear water).",
        )
        self.c3_veil_override = ViewerCheckbox(
            "Override veiling light",
            False,
            cb_hook=self._veil_override_changed,
            hint="Replace the learned water colour (c_med) with the colour below.",
        )
        self.c4_veil_rgb = ViewerRGB(
            "Veiling light", DEFAULT_VEIL_SRGB, disabled=True, hint="Water colour (sRGB) when overridden."
        )
        self.c5_exposure = ViewerSlider(
            "Exposure (stops)", 0.0, -6.0, 6.0, 0.1, hint="Display gain 2^stops on the *_display colour outputs."
        )
        self.c6_srgb = ViewerCheckbox(
            "sRGB display",
            linear_data,
            hint="Encode the *_display colour outputs as sRGB (on by default for linear data).",
        )

    def _veil_override_changed(self, element: ViewerCheckbox) -> None:
        if self.c4_veil_rgb.gui_handle is not None:
            self.c4_veil_rgb.set_disabled(not element.value)

    def veil_rgb(self) -> Optional[Tuple[float, float, float]]:
        """The overriding veiling light in the model's colour space, or ``None``."""
        if not self.c3_veil_override.value:
            return None
        rgb = torch.tensor([float(c) for c in self.c4_veil_rgb.value]) / 255.0
        if self.linear_data:  # the picker is sRGB, like every colour picker
            rgb = srgb_to_linear(rgb)
        return tuple(float(c) for c in rgb)  # type: ignore[return-value]

    def medium(self, medium: MediumOutputs) -> MediumOutputs:
        """``medium`` as the water controls set it (itself at their defaults)."""
        return override_medium(medium, float(self.c2_density.value), self.veil_rgb())

    def display_outputs(self, outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """:func:`display_outputs` with the Water, exposure and sRGB controls' current values."""
        return display_outputs(outputs, **self._display_settings())

    def display_sources(self, name: str) -> Tuple[str, ...]:
        """:func:`display_sources` with the Water control's current value."""
        return display_sources(name, water=bool(self.c1_water.value))

    def display_output(self, name: str, outputs: Mapping[str, Tensor]) -> Tensor:
        """:func:`display_output` with the Water, exposure and sRGB controls' current values."""
        return display_output(name, outputs, **self._display_settings())

    def _display_settings(self) -> dict:
        return dict(water=bool(self.c1_water.value), exposure=float(self.c5_exposure.value), srgb=bool(self.c6_srgb.value))

    def forward(self, *args, **kwargs) -> None:  # pragma: no cover - holder only
        raise TypeError("SeathruViewerControls only holds viewer elements; it is not callable")
