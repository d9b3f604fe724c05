"""The synthetic scene's cameras: an LLFF-like forward-facing rig, pinhole intrinsics and
per-pixel rays. Poses are camera-to-world in nerfstudio's OpenGL convention (the camera looks
along its -z, +y up, +x right); pixel centres sit at +0.5."""

from __future__ import annotations

import math
from typing import Dict

import numpy as np

from seathru_nerfstudio.data.synthetic.scene import Geometry

HORIZONTAL_FOV_DEG = 60.0

RIG_HALF_EXTENT = (0.3, 0.2)  # camera centres inside a 0.6 m x 0.4 m ellipse in the z=0 plane
LOOK_AT = np.array([0.0, -0.15, -1.4])
GOLDEN_FRACTION = (math.sqrt(5.0) - 1.0) / 2.0


def look_at(centre: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """4x4 camera-to-world, OpenGL convention (camera looks along its -z, +y up)."""
    z = centre - target
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, centre
    return c2w


def make_poses(rng: np.random.Generator, num_views: int, geometry: Geometry = Geometry()) -> np.ndarray:
    """Forward-facing rig: sunflower pattern filling an ellipse, jittered, small rotations; with
    ``geometry.rig_depth`` the centres also step back along +z by a low-discrepancy fraction of
    it (no random draws, so the other views' poses do not change)."""
    golden = math.pi * (3.0 - math.sqrt(5.0))
    poses = []
    for k in range(num_views):
        r = math.sqrt((k + 0.5) / num_views)
        a = k * golden
        rig = geometry.rig_scale
        back = geometry.rig_depth * ((k * GOLDEN_FRACTION) % 1.0)
        centre = np.array([rig * RIG_HALF_EXTENT[0] * r * math.cos(a), rig * RIG_HALF_EXTENT[1] * r * math.sin(a), back])
        centre += rng.uniform(-0.02, 0.02, size=3)
        target = LOOK_AT * geometry.scene_scale + rng.uniform(-0.06, 0.06, size=3)
        roll = math.radians(rng.uniform(-2.0, 2.0))
        poses.append(look_at(centre, target, roll))
    return np.stack(poses)


def intrinsics(width: int, height: int) -> Dict[str, float]:
    fl = 0.5 * width / math.tan(math.radians(HORIZONTAL_FOV_DEG) / 2.0)
    return {"fl_x": fl, "fl_y": fl, "cx": width / 2.0, "cy": height / 2.0}


def pixel_rays(c2w: np.ndarray, K: Dict[str, float], u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit world ray directions for pixel coordinates (u right, v down; pixel centres at +0.5)."""
    dc = np.stack([(u - K["cx"]) / K["fl_x"], -(v - K["cy"]) / K["fl_y"], -np.ones_like(u)], axis=-1)
    dw = dc @ c2w[:3, :3].T
    return dw / np.linalg.norm(dw, axis=-1, keepdims=True)

