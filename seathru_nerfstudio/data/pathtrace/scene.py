"""The path-traced scene: a layout drawn from a seed (numpy only) and its Mitsuba 3 scene dict.

World: metres, y up, seabed / ground around ``y = 0``, cameras look roughly along ``-z``.
Poses are camera-to-world in nerfstudio's OpenGL convention (camera looks along its ``-z``,
``+y`` up, ``+x`` right), with the intrinsics of :func:`seathru_nerfstudio.data.synthetic.
cameras.intrinsics` (60 degree horizontal field of view, pixel centres at +0.5).

Three renders of one layout (``mode``):

* ``"medium"``: the sensor sits in the medium (water or fog); every camera path is attenuated
  and scattered: the in-medium image ``I``.
* ``"clean"``: the SeaThru ``J`` term. The sensor is in no medium, and every surface is a medium
  transition whose exterior is the medium. A camera ray therefore reaches the first surface
  unattenuated; after the bounce Mitsuba's volumetric path tracers continue in
  ``si.target_medium(d)`` (the medium), and their shadow rays start there too, so the surface
  is lit exactly as in the medium: radiance leaving the surface, not attenuated on the way to
  the camera. (``volpathmis``: ``dr::masked(medium, has_medium_trans) = si.target_medium(ray.d)``
  after BSDF sampling, and the same in ``sample_emitter``.)
* ``"dry"``: no medium anywhere, same sun and sky: the medium-free render.

The medium is a large box (the water body, or the fog layer) whose top face is the surface, with
a null BSDF, so light enters through it unrefracted; its sides lie 150 m away, where no light
through them survives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Literal

import numpy as np
import numpy.typing as npt

from seathru_nerfstudio.data.pathtrace.presets import Preset
from seathru_nerfstudio.data.synthetic.cameras import HORIZONTAL_FOV_DEG, look_at

Mode = Literal["medium", "clean", "dry"]
MODES = ("medium", "clean", "dry")
BODY_HALF_WIDTH = 150.0
"""Half width (m) of the medium box: light entering through its sides is attenuated by at least
``exp(-150 sigma_t)``."""
BODY_DEPTH_BELOW = 150.0
"""The medium box reaches this far (m) below y = 0: past the seabed's drop-off, open water."""
TEXTURE_SIZE = 128
NUM_OBJECTS = 9


@dataclass
class SceneObject:
    kind: Literal["rock", "box"]
    centre: npt.NDArray[np.float64]
    """(3,) metres."""
    size: npt.NDArray[np.float64]
    """(3,) half extents along x, y, z (m) before the rotation."""
    yaw_deg: float
    texture: npt.NDArray[np.float32]
    """(T, T, 3) linear albedo in [0, 1]."""


@dataclass
class Layout:
    """Everything random about a scene, drawn once from the seed."""

    objects: List[SceneObject]
    bed_texture: npt.NDArray[np.float32]
    bed_waves: npt.NDArray[np.float64]
    """(K, 4) rows (amplitude m, kx, kz 1/m, phase) of the seabed's height undulations."""
    poses: npt.NDArray[np.float64]
    """(N, 4, 4) camera-to-world, nerfstudio / OpenGL convention."""


def tileable_noise(rng: np.random.Generator, size: int, slope: float) -> npt.NDArray[np.float64]:
    """(size, size) periodic noise with power spectrum ~ 1 / f^slope, scaled to [0, 1].

    White noise filtered in Fourier space: periodic, so a texture that repeats has no seam."""
    f = np.fft.fftfreq(size)
    radius = np.hypot(f[:, None], f[None, :])
    radius[0, 0] = 1.0
    spectrum = np.fft.fft2(rng.standard_normal((size, size))) / radius ** (slope / 2.0)
    spectrum[0, 0] = 0.0
    noise = np.real(np.fft.ifft2(spectrum))
    return (noise - noise.min()) / max(float(np.ptp(noise)), 1e-12)


def make_texture(rng: np.random.Generator, base: npt.NDArray[np.float64], accent: npt.NDArray[np.float64]) -> npt.NDArray[np.float32]:
    """(T, T, 3) albedo: ``base`` colour modulated by multi-scale noise, with ``accent`` blotches,
    and fine grain down to a few texels (the features structure from motion matches)."""
    shade = 0.45 + 0.55 * tileable_noise(rng, TEXTURE_SIZE, 1.6)
    grain = tileable_noise(rng, TEXTURE_SIZE, 0.6)
    blotch = tileable_noise(rng, TEXTURE_SIZE, 2.4) > 0.62
    colour = np.where(blotch[..., None], accent, base) * (shade * (0.75 + 0.5 * grain))[..., None]
    return np.clip(colour, 0.02, 0.9).astype(np.float32)


_PALETTE = np.array(
    [[0.55, 0.45, 0.35], [0.40, 0.40, 0.42], [0.70, 0.35, 0.25], [0.30, 0.50, 0.30],
     [0.75, 0.65, 0.40], [0.55, 0.30, 0.50], [0.80, 0.78, 0.72], [0.35, 0.30, 0.25]]
)


def bed_height(waves: npt.NDArray[np.float64], x: npt.NDArray[np.float64], z: npt.NDArray[np.float64], drop_off: bool, scale: float) -> npt.NDArray[np.float64]:
    """Seabed / ground height (m) at (x, z): gentle undulations; with ``drop_off`` it falls away
    (quadratically, steeper than the views) beyond 18 ``scale`` m ahead or 14 ``scale`` m aside."""
    h = np.zeros_like(x, dtype=np.float64)
    for amplitude, kx, kz, phase in waves:
        h += amplitude * np.sin(kx * x + kz * z + phase)
    if drop_off:
        ahead = np.maximum(0.0, -z - 18.0 * scale)
        aside = np.maximum(0.0, np.abs(x) - 14.0 * scale)
        h -= 0.4 * (ahead**2 + aside**2) / scale
    return h


def make_poses(rng: np.random.Generator, num_views: int, preset: Preset) -> npt.NDArray[np.float64]:
    """(N, 4, 4) camera-to-world: a rig that sweeps 4 m sideways and 3 m in depth (times the
    preset's scene scale, low-discrepancy depth steps), slightly up and down, aimed at the
    scene's centre with jitter, roll within 2 degrees."""
    s = preset.scene_scale
    golden = (math.sqrt(5.0) - 1.0) / 2.0
    poses = []
    for k in range(num_views):
        t = k / max(1, num_views - 1)
        x = (t - 0.5) * 4.0 * s
        z = ((k * golden) % 1.0 - 0.5) * 3.0 * s
        y = preset.camera_height + 0.2 * math.sin(3.0 * math.pi * t)
        target = np.array([0.35 * x, 0.5, -7.0 * s]) + rng.normal(0.0, 0.15, size=3)
        poses.append(look_at(np.array([x, y, z]), target, math.radians(rng.uniform(-2.0, 2.0))))
    return np.stack(poses)


def make_layout(seed: int, num_views: int, preset: Preset) -> Layout:
    """Seabed, objects and cameras for ``seed``. Objects stand on the seabed at horizontal
    distances stratified over 2.2-11.5 m (times the scene scale) from the rig's centre, within
    the field of view, so their ranges from the cameras span about 1.5-12 m."""
    rng = np.random.default_rng([seed, 11])
    s = preset.scene_scale
    waves = np.stack([rng.uniform(0.03, 0.12, 4), rng.uniform(-0.8, 0.8, 4), rng.uniform(-0.8, 0.8, 4), rng.uniform(0, 2 * np.pi, 4)], axis=1)
    bed_texture = make_texture(rng, np.array([0.62, 0.56, 0.44]), np.array([0.35, 0.33, 0.30]))
    objects = []
    for i in range(NUM_OBJECTS):
        distance = s * (2.2 + (11.5 - 2.2) * (i + rng.uniform(0.1, 0.9)) / NUM_OBJECTS)
        azimuth = math.radians(rng.uniform(-24.0, 24.0))
        x, z = distance * math.sin(azimuth), -distance * math.cos(azimuth)
        size = s * rng.uniform(0.25, 0.45) * (1.0 + distance / (8.0 * s)) * np.array([1.0, rng.uniform(0.7, 1.3), rng.uniform(0.8, 1.2)])
        kind = "box" if i % 3 == 1 else "rock"
        y = float(bed_height(waves, np.array(x), np.array(z), preset.drop_off, s)) + size[1] * (0.55 if kind == "rock" else 0.8)
        colours = _PALETTE[rng.choice(len(_PALETTE), 2, replace=False)]
        objects.append(SceneObject(kind, np.array([x, y, z]), size, rng.uniform(0, 90), make_texture(rng, colours[0], colours[1])))
    poses = make_poses(np.random.default_rng([seed, 12]), num_views, preset)
    return Layout(objects=objects, bed_texture=bed_texture, bed_waves=waves, poses=poses)


def grid_mesh(u: npt.NDArray[np.float64], v: npt.NDArray[np.float64], xyz: npt.NDArray[np.float64]):
    """Faces (F, 3) and uv (V, 2) of a (R, C) grid of vertices ``xyz`` (R, C, 3)."""
    rows, cols = u.shape
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return xyz.reshape(-1, 3), faces, np.stack([u, v], -1).reshape(-1, 2)


def bed_mesh(layout: Layout, preset: Preset):
    """The seabed / ground as a height field: 30 x 50 m around the rig (water), 600 m wide in
    air so the ground reaches the horizon. uv repeat every 3 m."""
    s = preset.scene_scale
    half, near, far, n = (25.0 * s, 8.0 * s, 45.0 * s, 160) if preset.drop_off else (300.0, 20.0, 600.0, 200)
    # denser vertices near the rig: a square-law spacing
    t = np.linspace(-1.0, 1.0, n)
    xs = half * np.sign(t) * t**2
    zs = near - (near + far) * np.linspace(0.0, 1.0, n) ** 2
    x, z = np.meshgrid(xs, zs)
    y = bed_height(layout.bed_waves, x, z, preset.drop_off, s)
    # the textured ground's normal points up: faces wind counter-clockwise seen from above
    vertices, faces, uv = grid_mesh(x / 3.0, z / 3.0, np.stack([x, y, z], -1))
    return vertices, faces[:, [0, 2, 1]], uv


def rock_mesh(obj: SceneObject, seed: int):
    """A displaced, squashed sphere (a rock) of ``obj.size`` half extents, uv from longitude /
    latitude (texture repeated twice around)."""
    rng = np.random.default_rng(seed)
    theta, phi = np.meshgrid(np.linspace(0.0, np.pi, 24), np.linspace(0.0, 2 * np.pi, 41), indexing="ij")
    bumps = tileable_noise(rng, 64, 2.2)
    r = 0.8 + 0.4 * bumps[(theta / np.pi * 31).astype(int), (phi / (2 * np.pi) * 63).astype(int) % 63]
    r[:, -1] = r[:, 0]  # close the seam
    r[0, :], r[-1, :] = r[0, 0], r[-1, 0]
    unit = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1) * r[..., None]
    yaw = math.radians(obj.yaw_deg)
    rot = np.array([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]])
    xyz = (unit * obj.size) @ rot.T + obj.centre
    vertices, faces, uv = grid_mesh(phi / np.pi, theta / np.pi, xyz)
    return vertices, faces[:, [0, 2, 1]], uv


def write_meshes(mi: Any, layout: Layout, preset: Preset, folder: Path) -> Dict[str, Path]:
    """Write the seabed and the rocks as PLY files (Mitsuba's own writer) into ``folder``."""
    meshes = {"bed": bed_mesh(layout, preset)}
    for i, obj in enumerate(layout.objects):
        if obj.kind == "rock":
            meshes[f"object_{i:02d}"] = rock_mesh(obj, seed=1000 + i)
    paths = {}
    for name, (vertices, faces, uv) in meshes.items():
        mesh = mi.Mesh(name, len(vertices), len(faces), has_vertex_normals=False, has_vertex_texcoords=True)
        params = mi.traverse(mesh)
        params["vertex_positions"] = np.ravel(vertices).astype(np.float32)
        params["faces"] = np.ravel(faces).astype(np.uint32)
        params["vertex_texcoords"] = np.ravel(uv).astype(np.float32)
        params.update()
        paths[name] = folder / f"{name}.ply"
        mesh.write_ply(str(paths[name]))
    return paths


def sky_bitmap(preset: Preset, height: int = 128) -> npt.NDArray[np.float32]:
    """(H, 2H, 3) lat-long sky radiance in Mitsuba's envmap layout (pixel (u, v) looks along
    ``y = cos(pi v)``, ``x = sin(pi v) sin(2 pi u)``, ``z = -sin(pi v) cos(2 pi u)``): zenith to
    horizon linear in sin(elevation), a dim ground colour below the horizon (hidden by the
    ground); with ``preset.sun_radius_deg > 0`` the sun is a disc of that angular radius whose
    radiance gives the irradiance ``preset.sun_irradiance`` (radiance = E / solid angle)."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(2 * height) + 0.5) / (2 * height)
    theta, phi = np.meshgrid(np.pi * v, 2 * np.pi * u, indexing="ij")
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    w = np.clip(d[..., 1], 0.0, 1.0)[..., None]
    sky = (1 - w) * np.array(preset.sky_horizon) + w * np.array(preset.sky_zenith)
    sky[d[..., 1] < 0] = 0.2 * np.array(preset.sky_horizon)
    if preset.sun_radius_deg > 0:
        radius = math.radians(preset.sun_radius_deg)
        disc = d @ sun_direction(preset) >= math.cos(radius)
        # the texels' own solid angle, so the map's discrete disc carries exactly the irradiance
        texel = (np.pi / height) * (2 * np.pi / (2 * height)) * np.sin(theta)
        sky[disc] += np.array(preset.sun_irradiance) / float(texel[disc].sum())
    return sky.astype(np.float32)


def sensor_to_world(c2w: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Mitsuba's camera frame (looks along +z, +y up, +x to the image's left) from a nerfstudio
    camera-to-world (looks along -z, +x right): flip x and z."""
    return c2w @ np.diag([-1.0, 1.0, -1.0, 1.0])


def medium_dict(preset: Preset) -> Dict[str, Any]:
    return {
        "type": "homogeneous",
        "sigma_t": {"type": "rgb", "value": list(preset.sigma_t)},
        "albedo": {"type": "rgb", "value": list(preset.albedo)},
        "phase": {"type": "hg", "g": preset.g},
    }


def sensor_dict(mi: Any, c2w, width: int, height: int, spp: int, medium: Any = None) -> Dict[str, Any]:
    """A pinhole (box pixel filter: each pixel averages its own footprint), in ``medium`` if given."""
    sensor = {
        "type": "perspective",
        "fov": HORIZONTAL_FOV_DEG,
        "fov_axis": "x",
        "near_clip": 0.001,
        "to_world": mi.ScalarTransform4f(sensor_to_world(np.asarray(c2w, dtype=np.float64))),
        "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp},
    }
    if medium is not None:
        sensor["medium"] = medium
    return sensor


def scene_dict(mi: Any, layout: Layout, preset: Preset, meshes: Dict[str, Path], mode: Mode, medium: Any, max_depth: int) -> Dict[str, Any]:
    """The Mitsuba scene (without its sensor: each view passes its own) for ``mode``.

    ``medium`` is the loaded medium object (None for ``dry`` or without a medium); surfaces get it
    as their exterior, the box of the water body / fog layer as its interior."""
    in_medium = medium is not None and mode != "dry"
    sun_dir = sun_direction(preset)
    scene: Dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "volpathmis", "max_depth": max_depth},
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky_bitmap(preset))},
    }
    if preset.sun_radius_deg <= 0:
        scene["sun"] = {"type": "directional", "direction": list(-sun_dir), "irradiance": {"type": "rgb", "value": list(preset.sun_irradiance)}}

    def surface(texture: npt.NDArray[np.float32]) -> Dict[str, Any]:
        shape: Dict[str, Any] = {"bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(texture), "wrap_mode": "repeat", "raw": True}}}
        if in_medium:
            shape["exterior"] = medium
        return shape

    scene["bed"] = {"type": "ply", "filename": str(meshes["bed"]), **surface(layout.bed_texture)}
    for i, obj in enumerate(layout.objects):
        name = f"object_{i:02d}"
        if obj.kind == "rock":
            scene[name] = {"type": "ply", "filename": str(meshes[name]), **surface(obj.texture)}
        else:
            to_world = mi.ScalarTransform4f().translate(obj.centre.tolist()).rotate([0, 1, 0], obj.yaw_deg).scale(obj.size.tolist())
            scene[name] = {"type": "cube", "to_world": to_world, **surface(obj.texture)}
    if in_medium:
        top = float(preset.layer_top)
        centre_y = 0.5 * (top - BODY_DEPTH_BELOW)
        half_y = 0.5 * (top + BODY_DEPTH_BELOW)
        scene["body"] = {
            "type": "cube",
            "to_world": mi.ScalarTransform4f().translate([0.0, centre_y, 0.0]).scale([BODY_HALF_WIDTH, half_y, BODY_HALF_WIDTH]),
            "bsdf": {"type": "null"},
            "interior": medium,
        }
    return scene


def sun_direction(preset: Preset) -> npt.NDArray[np.float64]:
    """Unit vector towards the sun (world): behind the rig (+z), so the faces seen are lit."""
    el, az = math.radians(preset.sun_elevation_deg), math.radians(preset.sun_azimuth_deg)
    return np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
