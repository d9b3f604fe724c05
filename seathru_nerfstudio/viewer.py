"""Water on, water off: SeaThru-NeRF in nerfstudio's live viewer and in ``ns-render``.

What this adds (issue #4), with the hooks in :mod:`seathru_nerfstudio.model`:

* **Controls** (:class:`SeathruViewerControls`, nerfstudio ``ViewerElement`` s, so the viewer of
  ``ns-train`` and ``ns-viewer`` shows them under *Custom Elements*): a ``Water`` checkbox
  that switches ``rgb`` between the image in the medium and the clean image; a water density
  scale (0x-3x on ``sigma_attn`` and ``sigma_bs``) and a veiling-light colour override that
  re-simulate other water; and a display transform for linear data (exposure in stops, sRGB
  encoding; the encoding is on by default when ``color_space == "linear"``).
* **Display renders**: camera renders for the viewer and for ``ns-render`` (recognised by
  their caller, nerfstudio's viewer render thread or ``nerfstudio/scripts/render.py``, since
  ``ns-render`` only loads the saved config) get the overrides and are tone mapped for
  display; the medium densities are normalised to ``[0, 1]`` per image (their hue, i.e.
  which channel the water takes most, is what a map of them can show); and an extra output
  ``water_split`` shows the image in the medium on the left half and the clean image on the
  right half (``ns-render ... --rendered-output-names water_split``).

No side effects: nothing here is a parameter or a buffer (the state dict is unchanged), and
nothing applies while the model trains (``model.training``), in the losses, or to any other
caller of ``model.get_outputs_for_camera`` (``ns-eval``, benchmarks, scripts get plain linear
outputs). :func:`linear_outputs` forces linear outputs (even inside a display caller) and
:class:`seathru_nerfstudio.pipeline.SeathruPipeline` wraps every evaluation in it; the
model's ``get_image_metrics_and_images`` never measures display values (:func:`linear_view`).
:func:`display_renders` asks for display renders explicitly.

Safe binding: :func:`install_loopback_default` makes the viewer of our models listen on
``127.0.0.1`` unless ``--viewer.websocket-host`` is given on the command line (``ns-viewer``
would otherwise use nerfstudio's default ``0.0.0.0``, whatever the saved config says).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterator, Optional, Tuple

import torch
from torch import Tensor, nn

from nerfstudio.viewer.viewer_elements import ViewerCheckbox, ViewerRGB, ViewerSlider

from seathru_nerfstudio.medium_field import MediumOutputs

LOOPBACK = "127.0.0.1"
"""Where our viewer listens unless ``--viewer.websocket-host`` says otherwise."""

SPLIT_OUTPUT = "water_split"
"""Extra display output: left half in the medium (``rgb``), right half clean."""
COLOUR_OUTPUTS = ("rgb", "clean", "direct", "backscatter", "medium_rgb", SPLIT_OUTPUT)
"""Linear colours: exposure and sRGB encoding apply to them."""
DENSITY_OUTPUTS = ("medium_attenuation", "medium_backscatter")
"""Densities per scene unit: shown normalised by their maximum over the image."""

DEFAULT_VEIL_SRGB = (30, 110, 160)
"""Initial colour of the veiling-light picker (8-bit sRGB, a deep blue-green)."""
SPLIT_LINE = 0.9
"""Grey level of the one-pixel line between the two halves of ``water_split``."""


def linear_to_srgb(x: Tensor) -> Tensor:
    """sRGB encoding (IEC 61966-2-1) of linear values in ``[0, 1]``."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055)


def srgb_to_linear(x: Tensor) -> Tensor:
    """Inverse of :func:`linear_to_srgb`."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)


@dataclass(frozen=True)
class DisplaySettings:
    """One snapshot of the controls, taken once per rendered image."""

    water: bool = True
    """``False``: ``rgb`` shows the clean image."""
    density_scale: float = 1.0
    """Multiplies ``sigma_attn`` and ``sigma_bs``."""
    veil_rgb: Optional[Tuple[float, float, float]] = None
    """Replaces ``c_med`` (linear, in the model's colour space) when set."""
    exposure: float = 0.0
    """Display gain ``2**exposure``."""
    srgb: bool = True
    """Encode linear colours as sRGB for display."""

    @property
    def changes_medium(self) -> bool:
        """Whether the render itself (not just its display) differs from the trained model's."""
        return self.density_scale != 1.0 or self.veil_rgb is not None


class SeathruViewerControls(nn.Module):
    """The viewer controls, as nerfstudio ``ViewerElement`` attributes.

    nerfstudio's viewer finds them by walking the pipeline's attributes and ``nn.Module``
    children (``parse_object``), hence an ``nn.Module``; it holds no parameters or buffers,
    so checkpoints do not change. The attribute names set the order in the GUI (nerfstudio
    sorts them). Without a GUI (``ns-render``, tests) each element's value is its default;
    setting ``element.value`` then changes the default.
    """

    def __init__(self, linear_data: bool) -> None:
        super().__init__()
        self.linear_data = linear_data
        self.c1_water = ViewerCheckbox(
            "Water", True, hint="Off: 'rgb' shows the scene without the water (the 'clean' output)."
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
            "Exposure (stops)", 0.0, -6.0, 6.0, 0.1, hint="Display gain 2^stops on the colour outputs."
        )
        self.c6_srgb = ViewerCheckbox(
            "sRGB display",
            linear_data,
            hint="Encode the linear colour outputs as sRGB (on by default for linear data).",
        )
        install_loopback_default()

    def _veil_override_changed(self, element: ViewerCheckbox) -> None:
        if self.c4_veil_rgb.gui_handle is not None:
            self.c4_veil_rgb.set_disabled(not element.value)

    def settings(self) -> DisplaySettings:
        veil = None
        if self.c3_veil_override.value:
            rgb = torch.tensor([float(c) for c in self.c4_veil_rgb.value]) / 255.0
            if self.linear_data:  # the picker is sRGB, like every colour picker
                rgb = srgb_to_linear(rgb)
            veil = tuple(float(c) for c in rgb)
        return DisplaySettings(
            water=bool(self.c1_water.value),
            density_scale=float(self.c2_density.value),
            veil_rgb=veil,  # type: ignore[arg-type]
            exposure=float(self.c5_exposure.value),
            srgb=bool(self.c6_srgb.value),
        )

    def forward(self, *args: Any, **kwargs: Any) -> None:  # pragma: no cover - holder only
        raise TypeError("SeathruViewerControls only holds viewer elements; it is not callable")


def controls_of(model: nn.Module) -> Optional[SeathruViewerControls]:
    """The model's controls, if it is a SeaThru model."""
    controls = getattr(model, "viewer_controls", None)
    return controls if isinstance(controls, SeathruViewerControls) else None


# --- which renders get the overrides and the display transform ----------------------------


class _ThreadState(threading.local):
    settings: Optional[DisplaySettings] = None
    linear_depth: int = 0
    display_depth: int = 0


_THREAD = _ThreadState()
# Thread-local: the viewer renders in its own threads while ns-train trains and evaluates.

DISPLAY_CALLERS = tuple(
    os.path.join("nerfstudio", *parts)
    for parts in (
        ("viewer", "render_state_machine.py"),  # the viewer's render threads
        ("viewer_legacy", "server", "render_state_machine.py"),
        ("scripts", "render.py"),  # ns-render
    )
)
"""Source files of nerfstudio whose camera renders are shown to a person, not measured."""


@contextmanager
def linear_outputs() -> Iterator[None]:
    """Within this context (in this thread) the model renders plain linear outputs: no
    display transform, no ``water_split``, no viewer overrides. For metrics; wins over
    :func:`display_renders`."""
    _THREAD.linear_depth += 1
    try:
        yield
    finally:
        _THREAD.linear_depth -= 1


@contextmanager
def display_renders() -> Iterator[None]:
    """Within this context (in this thread) camera renders are display renders, as in the
    viewer and ``ns-render`` (for scripts of our own that show images)."""
    _THREAD.display_depth += 1
    try:
        yield
    finally:
        _THREAD.display_depth -= 1


def _called_for_display() -> bool:
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_code.co_filename.endswith(DISPLAY_CALLERS):
            return True
        frame = frame.f_back
    return False


class DisplayOutputs(dict):
    """Outputs of a display render. ``linear`` holds the outputs before the display transform
    (rendered with ``settings``' medium overrides)."""

    def __init__(self, display: Dict[str, Tensor], linear: Dict[str, Tensor], settings: DisplaySettings) -> None:
        super().__init__(display)
        self.linear = linear
        self.settings = settings


def linear_view(outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """The linear, untransformed outputs behind ``outputs`` (for metrics). Raises if the
    render used a different medium than the trained one (viewer overrides)."""
    if not isinstance(outputs, DisplayOutputs):
        return outputs
    if outputs.settings.changes_medium:
        raise RuntimeError(
            "these outputs were rendered with the viewer's water overrides; compute metrics inside "
            "seathru_nerfstudio.viewer.linear_outputs() (SeathruPipeline does this for evaluation)"
        )
    return outputs.linear


def display_active(model: nn.Module) -> bool:
    """Whether a camera render of ``model`` in this thread is a display render: one for the
    viewer or ``ns-render`` (or inside :func:`display_renders`), never while training, never
    inside :func:`linear_outputs`. Everything else (``ns-eval``, benchmarks, scripts) gets
    the plain linear outputs."""
    if model.training or _THREAD.linear_depth > 0 or controls_of(model) is None:
        return False
    return _THREAD.display_depth > 0 or _called_for_display()


def render_camera(
    model: nn.Module, ray_bundle: Any, render: Callable[[Any], Dict[str, Tensor]]
) -> Dict[str, Tensor]:
    """Hook of ``SeathruModel.get_outputs_for_camera_ray_bundle``: ``render`` (nerfstudio's
    chunked render) with the viewer's medium overrides, then the display transform."""
    if not display_active(model):
        return render(ray_bundle)
    controls = controls_of(model)
    assert controls is not None
    settings = controls.settings()
    previous = _THREAD.settings
    _THREAD.settings = settings
    try:
        outputs = render(ray_bundle)
    finally:
        _THREAD.settings = previous
    return display_outputs(outputs, settings)


def override_medium(model: nn.Module, medium: MediumOutputs) -> MediumOutputs:
    """Hook of ``SeathruModel.get_outputs``: the medium as the viewer's controls set it.
    Identity outside a display render (training, losses, evaluation)."""
    settings = _THREAD.settings
    if settings is None or model.training or not settings.changes_medium:
        return medium
    rgb = medium.rgb
    if settings.veil_rgb is not None:
        rgb = torch.tensor(settings.veil_rgb, dtype=rgb.dtype, device=rgb.device).expand_as(rgb)
    scale = settings.density_scale
    return MediumOutputs(rgb=rgb, sigma_attn=medium.sigma_attn * scale, sigma_bs=medium.sigma_bs * scale)


def tone(image: Tensor, settings: DisplaySettings) -> Tensor:
    """Exposure, then sRGB encoding (or a clamp): a linear colour ready to show."""
    image = image * (2.0**settings.exposure)
    return linear_to_srgb(image) if settings.srgb else image.clamp(0.0, 1.0)


def water_split(rgb: Tensor, clean: Tensor) -> Tensor:
    """Left half ``rgb`` (in the medium), right half ``clean``; ``[H, W, 3]``."""
    half = rgb.shape[1] // 2
    return torch.cat([rgb[:, :half], clean[:, half:]], dim=1)


def display_outputs(outputs: Dict[str, Tensor], settings: DisplaySettings) -> DisplayOutputs:
    """The display transform of a whole image's outputs (``[H, W, C]`` each)."""
    shown: Dict[str, Tensor] = dict(outputs)
    if "rgb" in outputs and "clean" in outputs:
        if not settings.water:
            shown["rgb"] = outputs["clean"]
        shown[SPLIT_OUTPUT] = water_split(outputs["rgb"], outputs["clean"])
    for name in COLOUR_OUTPUTS:
        if name in shown:
            shown[name] = tone(shown[name], settings)
    if SPLIT_OUTPUT in shown and shown[SPLIT_OUTPUT].shape[1] > 2:
        shown[SPLIT_OUTPUT][:, shown[SPLIT_OUTPUT].shape[1] // 2] = SPLIT_LINE
    for name in DENSITY_OUTPUTS:
        if name in shown:
            density = shown[name]
            shown[name] = (density / density.max().clamp_min(1e-12)).clamp(0.0, 1.0)
    return DisplayOutputs(shown, outputs, settings)


# --- safe default binding --------------------------------------------------------------------

HOST_FLAGS = ("--viewer.websocket-host", "--viewer.websocket_host")


def host_on_command_line(argv: Optional[list] = None) -> bool:
    """Whether the command line sets the viewer's host (the explicit opt-in)."""
    argv = sys.argv[1:] if argv is None else argv
    return any(arg.split("=", 1)[0] in HOST_FLAGS for arg in argv)


def _loopback_init(init: Callable) -> Callable:
    # nerfstudio's viewers take (config, log_filename, datapath, pipeline, ...); their
    # __init__ is wrapped by nerfstudio (no usable signature), so the positions are spelled out.
    @functools.wraps(init)
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        args = list(args)
        config = args[0] if args else kwargs.get("config")
        pipeline = args[3] if len(args) > 3 else kwargs.get("pipeline")
        model = getattr(pipeline, "model", None)
        if (
            config is not None
            and model is not None
            and controls_of(model) is not None
            and config.websocket_host != LOOPBACK
            and not host_on_command_line()
        ):
            config = dataclasses.replace(config, websocket_host=LOOPBACK)
            if args:
                args[0] = config
            else:
                kwargs["config"] = config
        init(self, *args, **kwargs)

    __init__._seathru_loopback = True  # type: ignore[attr-defined]
    return __init__


def install_loopback_default() -> None:
    """Make nerfstudio's viewers listen on loopback for our models unless the command line
    sets ``--viewer.websocket-host``.

    Needed because ``ns-viewer`` replaces the saved viewer config with its own command-line
    defaults (host ``0.0.0.0``). Patches ``Viewer.__init__`` (and the legacy viewer's) of the
    viewer modules already imported (``ns-train`` and ``ns-viewer`` import them before they
    build the model, which calls this); idempotent; other models are left alone.
    """
    for module_name, class_name in (
        ("nerfstudio.viewer.viewer", "Viewer"),
        ("nerfstudio.viewer_legacy.server.viewer_state", "ViewerLegacyState"),
    ):
        module = sys.modules.get(module_name)
        cls = getattr(module, class_name, None) if module is not None else None
        if cls is None or getattr(cls.__init__, "_seathru_loopback", False):
            continue
        cls.__init__ = _loopback_init(cls.__init__)


install_loopback_default()
