"""The physical parameters of ``seathru-pathtrace``'s presets.

Units: lengths in metres, coefficients in 1/m, radiance and irradiance in the renderer's
linear units (the stored images are ``exposure * radiance``, see :class:`Preset`). The world
is y-up; the seabed (or ground) lies around ``y = 0``; cameras look roughly along ``-z``.

Water's beam attenuation ``c = sigma_t`` (absorption + scattering) and single-scattering
albedo ``omega = sigma_s / sigma_t`` are per RGB channel; scattering uses a Henyey-Greenstein
phase function with mean cosine ``g`` (natural waters: 0.8-0.95; the lower end here, because
the sun's forward-scattered aureole is the path tracer's main source of noise, which grows as
``(1 + g) / (1 - g)^2``: a sun weaker than the sky (1.5 against about 3.5 on a level surface)
for the same reason). The ``coastal`` values are
those of a blue-green coastal water (c = 0.30, 0.17, 0.12 /m, red absorbed most); ``turbid``
is a green, particle-laden water (blue absorbed by dissolved organic matter, green least
attenuated); ``fog`` is a grey, mostly scattering layer of finite height over the ground;
``clear`` has no medium at all.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Dict, Literal, Optional, Tuple

RGB = Tuple[float, float, float]
MediumKind = Literal["water", "fog", "none"]
PresetName = Literal["coastal", "turbid", "fog", "clear"]

HOLDOUT_EVERY = 8
"""Views 0, 8, 16, ... are held out for val/test (3 of the default 24)."""


@dataclass(frozen=True)
class Preset:
    """One scene kind: its medium, its light and where the cameras are."""

    name: str
    medium: MediumKind
    sigma_t: RGB
    """Beam attenuation (extinction) per channel, 1/m; zeros without a medium."""
    albedo: RGB
    """Single-scattering albedo per channel (scattering / extinction), unitless."""
    g: float
    """Henyey-Greenstein mean cosine of the scattering angle."""
    layer_top: Optional[float]
    """Height (m, world y) of the medium's top face: the water surface or the fog's top; None
    without a medium."""
    camera_height: float
    """Camera height above the seabed / ground (m) at the rig's centre."""
    scene_scale: float
    """Object distances are multiplied by this (1: objects 1.5-12 m from the rig)."""
    sun_elevation_deg: float
    sun_azimuth_deg: float
    sun_irradiance: RGB
    """Irradiance of the sun on a surface facing it, above the medium."""
    sun_radius_deg: float
    """Angular radius of the sun's disc in the sky map; 0: a directional (point) sun."""
    sky_zenith: RGB
    sky_horizon: RGB
    """Sky radiance straight up and at the horizon (linear ramp in sin(elevation) between)."""
    exposure: float
    """Stored image = exposure x rendered radiance (then clipped to [0, 1] in the 16-bit PNGs)."""
    drop_off: bool
    """Water: the seabed falls away beyond ~18 m, so the far field is open water (range inf)."""
    spp: int = 256
    """Samples per pixel when ``--spp`` is not given: enough that the Monte Carlo noise on the
    display copy SfM sees is about 6 grey levels or less (Immerkaer's estimate on the lightness;
    at 256: coastal 5.7, fog 5.4, clear 2.7, turbid 12.2). Noise falls as 1/sqrt(spp)."""

    def to_json(self) -> Dict[str, object]:
        return asdict(self)


_SUN = dict(sun_elevation_deg=60.0, sun_azimuth_deg=30.0, sun_radius_deg=0.0)

PRESETS: Dict[str, Preset] = {
    "coastal": Preset(
        name="coastal", medium="water", sigma_t=(0.30, 0.17, 0.12), albedo=(0.60, 0.75, 0.80), g=0.80,
        layer_top=8.0, camera_height=1.6, scene_scale=1.0, sun_irradiance=(1.5, 1.5, 1.45),
        sky_zenith=(0.52, 0.82, 1.42), sky_horizon=(1.12, 1.28, 1.5), exposure=1.0, drop_off=True, **_SUN,
    ),
    "turbid": Preset(
        name="turbid", medium="water", sigma_t=(0.55, 0.35, 0.50), albedo=(0.65, 0.85, 0.70), g=0.85,
        layer_top=6.0, camera_height=1.3, scene_scale=0.6, sun_irradiance=(1.5, 1.5, 1.45),
        sky_zenith=(0.52, 0.82, 1.42), sky_horizon=(1.12, 1.28, 1.5), exposure=1.5, drop_off=True, **_SUN,
        spp=1024,  # high albedo and g: at 256 the noise (12.2) is above the texture, no view registers; 1024: 6.5
    ),
    "fog": Preset(
        name="fog", medium="fog", sigma_t=(0.12, 0.12, 0.12), albedo=(0.90, 0.90, 0.90), g=0.80,
        layer_top=8.0, camera_height=1.8, scene_scale=1.0, sun_irradiance=(1.5, 1.45, 1.4),
        sky_zenith=(0.45, 0.68, 1.2), sky_horizon=(0.98, 1.08, 1.28), exposure=0.6, drop_off=False, **_SUN,
    ),
    "clear": Preset(
        name="clear", medium="none", sigma_t=(0.0, 0.0, 0.0), albedo=(0.0, 0.0, 0.0), g=0.0,
        layer_top=None, camera_height=1.8, scene_scale=1.0, sun_irradiance=(2.2, 2.1, 2.0),
        sky_zenith=(0.30, 0.45, 0.80), sky_horizon=(0.65, 0.72, 0.85), exposure=0.6, drop_off=False, **_SUN,
    ),
}
