"""Synthetic forward-facing underwater / foggy scenes with exact ground truth.

``seathru-synth --output-dir DIR [--preset water|fog|none] [--seed N] ...`` ray-casts a small
analytic scene (a textured back wall with an irregular top edge, a ground plane, and a few
spheres and boxes) from an LLFF-like forward-facing rig and adds a scattering medium with the
SeaThru image formation model (as in Levy et al., CVPR 2023), per ray and per channel::

    I = J * exp(-beta_D * z) + B_inf * (1 - exp(-beta_B * z))

Conventions (all outputs):

* colours are **linear** radiance in [0, 1], stored as 16-bit RGB PNG (value / 65535);
* ``z`` is the **range**: Euclidean distance in metres from the camera centre to the first
  surface along the pixel-centre ray (not the z-depth); ``inf`` where the pixel sees nothing
  ("open water"), where ``I == B_inf`` exactly and the clean image ``J`` is 0;
* with ``--supersample N`` (default 2) the medium is applied to each of the N x N rays of a
  pixel before averaging, so the model holds per ray and only approximately per pixel at
  depth edges; ``--supersample 1`` makes every pixel follow the model exactly. A pixel whose
  centre ray misses but another of its rays hits an object gets the smallest hit range, so
  ``z == inf`` exactly when all of the pixel's rays see open water;
* world units are metres; camera-to-world poses use nerfstudio's OpenGL convention (camera
  looks along -z, +y up, +x right), world +y is up.

Layout of ``DIR``::

    transforms.json                 nerfstudio format, with train/val/test_filenames splits
    images/frame_00000.png          I (with medium), 16-bit linear RGB
    ground_truth/clean/frame_*.png  J (no medium), 16-bit linear RGB
    ground_truth/depth/frame_*.npy  float32 HxW range in metres, inf = open water
    ground_truth/medium.json        medium parameters (1/m) and generation settings

The output is deterministic given ``--seed`` (byte-identical files), and written atomically
(built in a temporary sibling folder and renamed into place).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple

import cv2
import numpy as np
import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

CONSOLE = Console(stderr=True)

PresetName = Literal["water", "turbid", "fog", "none"]

#: Medium presets: attenuation beta_D (1/m), backscatter beta_B (1/m), veiling light B_inf
#: (linear RGB). ``water`` is the paper's underwater *Fern* simulation (Sec. 5).
PRESETS: Dict[str, Dict[str, List[float]]] = {
    "water": {"beta_D": [1.3, 1.2, 0.9], "beta_B": [0.95, 0.85, 0.7], "B_inf": [0.07, 0.2, 0.39]},
    "turbid": {"beta_D": [0.62, 0.38, 0.46], "beta_B": [0.48, 0.32, 0.38], "B_inf": [0.04, 0.26, 0.18]},
    "fog": {"beta_D": [1.2, 1.2, 1.2], "beta_B": [1.2, 1.2, 1.2], "B_inf": [0.6, 0.6, 0.6]},
    "none": {"beta_D": [0.0, 0.0, 0.0], "beta_B": [0.0, 0.0, 0.0], "B_inf": [0.0, 0.0, 0.0]},
}

@dataclass(frozen=True)
class Geometry:
    """How a preset's scene is laid out, relative to the base scene (objects 0.76-2.6 m away)."""

    scene_scale: float = 1.0
    """Every primitive's position, size and texture scaled by this about the rig's origin."""
    near_scale: float = 1.0
    """The same for the nearest sphere, so that a scaled scene still has something close."""
    rig_scale: float = 1.0
    """Camera rig extent scaled by this."""


#: ``turbid``: green coastal water, a scene 3.5x deeper (objects about 1 to 8 m away).
GEOMETRY: Dict[str, Geometry] = {"turbid": Geometry(scene_scale=3.5, near_scale=1.4, rig_scale=1.5)}

HOLDOUT_EVERY = 5
"""Views 0, 5, 10, ... are held out for val/test."""

HORIZONTAL_FOV_DEG = 60.0


@dataclass
class SynthConfig:
    """Generate a synthetic forward-facing multi-view scene seen through water or fog."""

    output_dir: Path
    """Folder to create (must not exist or be empty, unless --overwrite)."""
    preset: PresetName = "water"
    """Medium: 'water' (paper's Fern simulation), 'turbid' (green coastal water, objects ~1-8 m),
    'fog' (grey, beta=1.2/m) or 'none' (clear)."""
    seed: int = 0
    """Random seed for scene layout, textures and camera jitter; same seed = identical files."""
    width: int = 160
    """Image width in pixels."""
    height: int = 120
    """Image height in pixels."""
    num_views: int = 20
    """Number of views; every 5th view (0, 5, 10, ...) is held out for val/test."""
    overwrite: bool = False
    """Replace the output folder if it exists and is non-empty."""
    supersample: int = 2
    """Anti-aliasing: supersample^2 rays per pixel, medium applied per ray; 1 = off (exact model per pixel)."""
    sfm_points_per_view: int = 300
    """Sparse depth like structure-from-motion's: this many textured pixels per view get their
    true z-depth in ``depth/`` (nerfstudio's ``depth_file_path``, 16-bit millimetres, 0 =
    unknown); 0: none. Open water and flat texture have no SfM points, as in a real capture."""


# ----------------------------------------------------------------------------------------------
# Procedural noise (deterministic integer hashing, no global RNG state)
# ----------------------------------------------------------------------------------------------

_U32 = np.uint32
_PX, _PY, _PZ = _U32(0x8DA6B343), _U32(0xD8163841), _U32(0xCB1AB31F)
_F1, _F2 = _U32(0x2C1B3C6D), _U32(0x297A2D39)
_S15, _S12 = _U32(15), _U32(12)
_INV32 = np.float32(1.0 / 4294967296.0)


def _finalize(h: np.ndarray) -> np.ndarray:
    """Avalanche a uint32 array in place-ish and map it to float32 in [0, 1)."""
    h ^= h >> _S15
    h *= _F1
    h ^= h >> _S12
    h *= _F2
    h ^= h >> _S15
    return h.astype(np.float32) * _INV32


def _cells(q: np.ndarray) -> np.ndarray:
    """Integer lattice cell of points (N, 3) as wrapping uint32 (N, 3)."""
    return np.floor(q).astype(np.int32).view(np.uint32)


def _hash01(c: np.ndarray, salt: int) -> np.ndarray:
    """Hash uint32 lattice cells (N, 3) to float32 in [0, 1) (deterministic, wraps mod 2^32)."""
    h = (c[:, 0] * _PX) ^ (c[:, 1] * _PY) ^ (c[:, 2] * _PZ) ^ _U32(salt & 0xFFFFFFFF)
    return _finalize(h)


def _value_noise(q: np.ndarray, salt: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] (float32) at points ``q`` (N, 3), lattice spacing 1."""
    fl = np.floor(q)
    f = (q - fl).astype(np.float32)
    f = f * f * (np.float32(3.0) - np.float32(2.0) * f)
    i = fl.astype(np.int32).view(np.uint32)
    s = _U32(salt & 0xFFFFFFFF)
    hx0 = i[:, 0] * _PX
    hx = (hx0 ^ s, (hx0 + _PX) ^ s)
    hy0 = i[:, 1] * _PY
    hy = (hy0, hy0 + _PY)
    hz0 = i[:, 2] * _PZ
    hz = (hz0, hz0 + _PZ)
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    vx = []
    for a in (0, 1):
        vy = []
        for b in (0, 1):
            hab = hx[a] ^ hy[b]
            v0 = _finalize(hab ^ hz[0])
            v1 = _finalize(hab ^ hz[1])
            vy.append(v0 + fz * (v1 - v0))
        vx.append(vy[0] + fy * (vy[1] - vy[0]))
    return vx[0] + fx * (vx[1] - vx[0])


def _fbm(q: np.ndarray, salt: int, octaves: int, lacunarity: float = 2.13) -> np.ndarray:
    """Fractal value noise in [0, 1]; octaves use non-integer frequency ratios and offsets so
    the result has no visible period."""
    total = np.zeros(len(q))
    amp, norm, freq = 1.0, 0.0, 1.0
    for o in range(octaves):
        shift = np.array([17.31, 5.77, 11.13]) * (o + 1)
        total += amp * _value_noise(q * freq + shift, salt + 1013 * o)
        norm += amp
        amp *= 0.6
        freq *= lacunarity
    return total / norm


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectorised HSV -> RGB; h in turns (wraps), s and v in [0, 1]. Returns (N, 3)."""
    h6 = (h % 1.0) * 6.0
    k = (np.array([5.0, 3.0, 1.0])[None, :] + h6[:, None]) % 6.0
    return v[:, None] - v[:, None] * s[:, None] * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


# ----------------------------------------------------------------------------------------------
# Scene description
# ----------------------------------------------------------------------------------------------


@dataclass
class _Texture:
    """Solid (3D) procedural texture, lengths in metres."""

    salt: int
    hue: float
    hue_spread: float
    sat: float
    noise_cell: float
    checker_cell: float
    checker_weight: float
    checker_rgb: np.ndarray
    stripe_dir: np.ndarray
    stripe_period: float
    stripe_weight: float
    blob_cell: float
    blob_prob: float
    offset: np.ndarray

    def albedo(self, p: np.ndarray) -> np.ndarray:
        """Diffuse albedo (N, 3) in [0.1, 0.95] at world points ``p`` (N, 3) in metres."""
        n = len(p)
        if n == 0:
            return np.zeros((0, 3))
        q = p + self.offset
        # Coarse hue/saturation field + fine multi-octave brightness noise.
        low = _value_noise(q / 0.4, self.salt + 1)
        hue = self.hue + self.hue_spread * (low - 0.5)
        sat = np.clip(self.sat * (0.6 + 0.8 * (1.0 - low)), 0.0, 1.0)
        fine = _fbm(q / self.noise_cell, self.salt + 2, 3)
        rgb = _hsv_to_rgb(hue, sat, 0.25 + 0.75 * fine)
        # Noise-warped 3D checkers (cell size varies locally -> not periodic).
        mid = _value_noise(q / 0.2 + 7.7, self.salt + 4) - 0.5
        cq = np.floor((q + (0.6 * self.checker_cell) * mid[:, None]) / self.checker_cell).astype(np.int64)
        chk = ((cq[:, 0] + cq[:, 1] + cq[:, 2]) & 1).astype(np.float64)[:, None]
        rgb = rgb * (1.0 - self.checker_weight * chk) + self.checker_weight * chk * self.checker_rgb
        # Wavy stripes along a random direction, darkening.
        phase = q @ self.stripe_dir / self.stripe_period + 2.5 * mid
        stripe = (np.sin(2.0 * np.pi * phase) > 0.3)[:, None]
        rgb = np.where(stripe, rgb * (1.0 - self.stripe_weight), rgb)
        # Random coloured blobs: at most one ball per jittered cell (solid Worley-like spots).
        cell = q / self.blob_cell
        ci = _cells(cell)
        local = cell - np.floor(cell)
        s = self.salt + 100
        present = _hash01(ci, s) < self.blob_prob
        rad = 0.15 + 0.2 * _hash01(ci, s + 1)
        d2 = np.zeros(n)
        for k in range(3):
            ck = rad + (1.0 - 2.0 * rad) * _hash01(ci, s + 2 + k)
            d2 += (local[:, k] - ck) ** 2
        inside = present & (d2 < rad**2)
        if np.any(inside):
            cj = ci[inside]
            bh = _hash01(cj, s + 10)
            bv = _hash01(cj, s + 11)
            bval = np.where(bv < 0.3, 0.12 + 0.1 * bv, 0.65 + 0.3 * bv)
            rgb[inside] = _hsv_to_rgb(bh, np.full(len(cj), 0.85), bval)
        return np.clip(rgb, 0.1, 0.95)


@dataclass
class _Prim:
    """Analytic primitive. kind: 'sphere' | 'box' | 'wall' (plane z=c) | 'ground' (plane y=c)."""

    kind: str
    texture: _Texture
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = 0.0
    half: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rot: np.ndarray = field(default_factory=lambda: np.eye(3))  # local -> world
    plane: float = 0.0
    bounds: Tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    top_amp: float = 0.0  # wall only: irregular top edge amplitude (m)
    tex_scale: float = 1.0  # the texture is evaluated at p / tex_scale
    _top_lut: Optional[Tuple[np.ndarray, np.ndarray]] = None

    def wall_top(self, x: np.ndarray) -> np.ndarray:
        """Height (m) of the wall's irregular top edge at world x (piecewise linear, 2 mm knots)."""
        if self._top_lut is None:
            xs = np.linspace(self.bounds[0], self.bounds[1], int(round((self.bounds[1] - self.bounds[0]) / 0.002)) + 1)
            q = np.stack([xs / (0.3 * self.tex_scale), np.zeros_like(xs), np.zeros_like(xs)], 1)
            bumps = _fbm(q, self.texture.salt + 77, 3).astype(np.float64) - 0.5
            self._top_lut = (xs, self.bounds[3] + 2.0 * self.top_amp * bumps)
        return np.interp(x, *self._top_lut)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Distance t along unit rays o + t d to the first hit in front (inf on miss).

        ``o`` is either one origin (3,) shared by all rays or per-ray origins (N, 3)."""
        n = len(d)
        t = np.full(n, np.inf)
        eps = 1e-6
        if self.kind in ("sphere", "box"):
            rad = self.radius if self.kind == "sphere" else float(np.linalg.norm(self.half))
            oc = o - self.centre
            b = d @ oc if oc.ndim == 1 else np.einsum("ij,ij->i", d, oc)
            c = (oc @ oc if oc.ndim == 1 else np.einsum("ij,ij->i", oc, oc)) - rad**2
            disc = b * b - c
            cand = np.flatnonzero((disc > 0) & (-b + np.sqrt(np.maximum(disc, 0.0)) > eps))
            if len(cand) == 0:
                return t
            if self.kind == "sphere":
                sq = np.sqrt(disc[cand])
                t0 = -b[cand] - sq
                t[cand] = np.where(t0 > eps, t0, -b[cand] + sq)
                return t
            # oriented box, slab test in the box frame on bounding-sphere candidates only
            ol = (oc if oc.ndim == 1 else oc[cand]) @ self.rot  # world -> local
            dl = d[cand] @ self.rot
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / dl
                ta = (-self.half - ol) * inv
                tb = (self.half - ol) * inv
            tnear = np.max(np.minimum(ta, tb), axis=1)
            tfar = np.min(np.maximum(ta, tb), axis=1)
            tt = np.where(tnear > eps, tnear, tfar)
            ok = (tnear <= tfar) & (tfar > eps) & np.isfinite(tt)
            t[cand[ok]] = tt[ok]
            return t
        ax = 2 if self.kind == "wall" else 1
        o_ax = o[ax] if o.ndim == 1 else o[:, ax]
        with np.errstate(divide="ignore", invalid="ignore"):
            tt = (self.plane - o_ax) / d[:, ax]
        ok = np.isfinite(tt) & (tt > eps)
        idx = np.flatnonzero(ok)
        p = (o if o.ndim == 1 else o[idx]) + tt[idx, None] * d[idx]
        a0, a1, b0, b1 = self.bounds
        if self.kind == "wall":  # x in [a0, a1], y in [b0, top(x)]
            inb = (p[:, 0] >= a0) & (p[:, 0] <= a1) & (p[:, 1] >= b0) & (p[:, 1] <= b1 + self.top_amp)
            inb[inb] &= p[inb, 1] <= self.wall_top(p[inb, 0])
        else:  # ground: x in [a0, a1], z in [b0, b1]
            inb = (p[:, 0] >= a0) & (p[:, 0] <= a1) & (p[:, 2] >= b0) & (p[:, 2] <= b1)
        t[idx[inb]] = tt[idx[inb]]
        return t

    def normal(self, p: np.ndarray) -> np.ndarray:
        """Outward unit normals (N, 3) at surface points ``p`` (N, 3)."""
        if self.kind == "sphere":
            return (p - self.centre) / self.radius
        if self.kind == "box":
            pl = (p - self.centre) @ self.rot
            rel = np.abs(pl) / self.half
            axis = np.argmax(rel, axis=1)
            nl = np.zeros_like(pl)
            rows = np.arange(len(p))
            nl[rows, axis] = np.sign(pl[rows, axis])
            return nl @ self.rot.T
        nrm = np.zeros_like(p)
        nrm[:, 2 if self.kind == "wall" else 1] = 1.0
        return nrm


@dataclass
class _Scene:
    prims: List[_Prim]
    light_dir: np.ndarray  # unit vector towards the light
    ambient: float = 0.45

    def trace(self, o: np.ndarray, d: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Nearest hit of unit rays: range t (inf on miss) and primitive index (-1 on miss)."""
        t = np.full(len(d), np.inf)
        idx = np.full(len(d), -1, dtype=np.int64)
        for k, prim in enumerate(self.prims):
            tk = prim.intersect(o, d)
            closer = tk < t
            t[closer] = tk[closer]
            idx[closer] = k
        return t, idx

    def shade(self, o: np.ndarray, d: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Clean linear radiance J (N, 3) (0 on miss) and range t (N,) in metres for unit rays."""
        t, idx = self.trace(o, d)
        J = np.zeros((len(d), 3))
        hit = np.flatnonzero(idx >= 0)
        if len(hit) == 0:
            return J, t
        hidx = idx[hit]
        p = o + t[hit, None] * d[hit]
        nrm = np.zeros_like(p)
        alb = np.zeros_like(p)
        for k, prim in enumerate(self.prims):
            m = np.flatnonzero(hidx == k)
            if len(m):
                nrm[m] = prim.normal(p[m])
                alb[m] = prim.texture.albedo(p[m] / prim.tex_scale)
        # Lambertian + ambient, with hard shadows cast by the objects (not by the wall/ground).
        ndl = np.clip(nrm @ self.light_dir, 0.0, None)
        lit_idx = np.flatnonzero(ndl > 0)
        ps = p[lit_idx] + 1e-4 * nrm[lit_idx]
        ls = np.broadcast_to(self.light_dir, ps.shape)
        blocked = np.zeros(len(ps), dtype=bool)
        for prim in self.prims:
            if prim.kind in ("sphere", "box"):
                blocked |= np.isfinite(prim.intersect(ps, ls))
        ndl[lit_idx[blocked]] = 0.0
        J[hit] = alb * (self.ambient + (1.0 - self.ambient) * ndl)[:, None]
        return J, t


def _random_texture(rng: np.random.Generator, salt: int) -> _Texture:
    sd = rng.normal(size=3)
    return _Texture(
        salt=salt,
        hue=float(rng.uniform()),
        hue_spread=float(rng.uniform(0.3, 0.8)),
        sat=float(rng.uniform(0.45, 0.85)),
        noise_cell=float(rng.uniform(0.035, 0.06)),
        checker_cell=float(rng.uniform(0.05, 0.12)),
        checker_weight=float(rng.uniform(0.25, 0.5)),
        checker_rgb=_hsv_to_rgb(np.array([rng.uniform()]), np.array([0.7]), np.array([0.85]))[0],
        stripe_dir=sd / np.linalg.norm(sd),
        stripe_period=float(rng.uniform(0.05, 0.11)),
        stripe_weight=float(rng.uniform(0.2, 0.45)),
        blob_cell=float(rng.uniform(0.09, 0.15)),
        blob_prob=float(rng.uniform(0.35, 0.6)),
        offset=rng.uniform(-50.0, 50.0, size=3),
    )


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


WALL_Z = -1.85
GROUND_Y = -0.7
WALL_TOP_Y = 0.22


def _build_scene(rng: np.random.Generator, geometry: Geometry = Geometry()) -> _Scene:
    """Scene in metres; cameras sit near z=0 looking towards -z. Wall at z=-1.85, ground at y=-0.7,
    open water above the wall's irregular top edge (~0.22 m); all of it times ``geometry``'s scales."""
    salt = int(rng.integers(0, 2**31))
    tex = lambda k: _random_texture(rng, salt + 7919 * k)  # noqa: E731
    j = lambda s: rng.uniform(-s, s, size=3)  # noqa: E731
    prims = [
        _Prim("wall", tex(0), plane=WALL_Z, bounds=(-3.0, 3.0, GROUND_Y, WALL_TOP_Y), top_amp=0.07),
        _Prim("ground", tex(1), plane=GROUND_Y, bounds=(-3.0, 3.0, WALL_Z, -0.2)),
        # near sphere (~0.7 m from the rig)
        _Prim("sphere", tex(2), centre=np.array([-0.33, -0.3, -0.88]) + j(0.03), radius=0.17 + rng.uniform(-0.015, 0.015)),
        # mid sphere resting near the ground
        _Prim("sphere", tex(3), centre=np.array([0.42, -0.45, -1.4]) + j(0.05), radius=0.24 + rng.uniform(-0.03, 0.03)),
        # rotated box on the ground
        _Prim(
            "box",
            tex(4),
            centre=np.array([-0.05, -0.5, -1.3]) + j(0.05) * np.array([1, 0, 1]),
            half=np.array([0.17, 0.2, 0.14]),
            rot=_rot_y(rng.uniform(0.3, 0.9)),
        ),
        # tall pillar, rising above the wall into open water
        _Prim(
            "box",
            tex(5),
            centre=np.array([0.15, -0.15, -1.62]) + j(0.05) * np.array([1, 0, 1]),
            half=np.array([0.07, 0.55, 0.07]),
            rot=_rot_y(rng.uniform(0.0, 1.5)) @ _rot_x(rng.uniform(-0.08, 0.08)),
        ),
        # far sphere, partly above the wall
        _Prim("sphere", tex(6), centre=np.array([-0.68, 0.05, -1.65]) + j(0.05), radius=0.18 + rng.uniform(-0.02, 0.02)),
        # far box
        _Prim(
            "box",
            tex(7),
            centre=np.array([0.8, -0.1, -1.62]) + j(0.05),
            half=np.array([0.14, 0.14, 0.14]),
            rot=_rot_y(rng.uniform(0, 1.5)) @ _rot_x(rng.uniform(0, 1.5)),
        ),
    ]
    for k, prim in enumerate(prims):
        _scale_prim(prim, geometry.near_scale if k == NEAR_SPHERE else geometry.scene_scale)
    prims[0].wall_top(np.zeros(1))  # build the edge lookup table now (renders run in threads)
    light = np.array([-0.4, 0.8, 0.45])
    return _Scene(prims=prims, light_dir=light / np.linalg.norm(light))


NEAR_SPHERE = 2
"""Index of the nearest sphere in :func:`_build_scene`'s list."""


def _scale_prim(prim: _Prim, factor: float) -> None:
    """Scale a primitive about the origin (the rig's centre): it looks the same from there,
    ``factor`` times farther away."""
    if factor == 1.0:
        return
    prim.centre = prim.centre * factor
    prim.radius *= factor
    prim.half = prim.half * factor
    prim.plane *= factor
    prim.bounds = tuple(b * factor for b in prim.bounds)
    prim.top_amp *= factor
    prim.tex_scale *= factor


# ----------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------

RIG_HALF_EXTENT = (0.3, 0.2)  # camera centres inside a 0.6 m x 0.4 m ellipse in the z=0 plane
LOOK_AT = np.array([0.0, -0.15, -1.4])


def _look_at(centre: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
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


def _make_poses(rng: np.random.Generator, num_views: int, geometry: Geometry = Geometry()) -> np.ndarray:
    """Forward-facing rig: sunflower pattern filling an ellipse, jittered, small rotations."""
    golden = math.pi * (3.0 - math.sqrt(5.0))
    poses = []
    for k in range(num_views):
        r = math.sqrt((k + 0.5) / num_views)
        a = k * golden
        rig = geometry.rig_scale
        centre = np.array([rig * RIG_HALF_EXTENT[0] * r * math.cos(a), rig * RIG_HALF_EXTENT[1] * r * math.sin(a), 0.0])
        centre += rng.uniform(-0.02, 0.02, size=3)
        target = LOOK_AT * geometry.scene_scale + rng.uniform(-0.06, 0.06, size=3)
        roll = math.radians(rng.uniform(-2.0, 2.0))
        poses.append(_look_at(centre, target, roll))
    return np.stack(poses)


def _intrinsics(width: int, height: int) -> Dict[str, float]:
    fl = 0.5 * width / math.tan(math.radians(HORIZONTAL_FOV_DEG) / 2.0)
    return {"fl_x": fl, "fl_y": fl, "cx": width / 2.0, "cy": height / 2.0}


def _pixel_rays(c2w: np.ndarray, K: Dict[str, float], u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit world ray directions for pixel coordinates (u right, v down; pixel centres at +0.5)."""
    dc = np.stack([(u - K["cx"]) / K["fl_x"], -(v - K["cy"]) / K["fl_y"], -np.ones_like(u)], axis=-1)
    dw = dc @ c2w[:3, :3].T
    return dw / np.linalg.norm(dw, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------------------------
# Image formation
# ----------------------------------------------------------------------------------------------


def apply_medium(
    J: np.ndarray, z: np.ndarray, beta_D: np.ndarray, beta_B: np.ndarray, B_inf: np.ndarray
) -> np.ndarray:
    """SeaThru model I = J exp(-beta_D z) + B_inf (1 - exp(-beta_B z)), per channel.

    J: (..., 3) linear clean radiance; z: (...) range in metres (inf = no object: I = B_inf);
    beta_D, beta_B in 1/m and B_inf linear, each (3,).
    """
    finite = np.isfinite(z)[..., None]
    zf = np.where(finite, z[..., None], 0.0)
    direct = np.where(finite, J * np.exp(-np.asarray(beta_D) * zf), 0.0)
    back_frac = np.where(finite, -np.expm1(-np.asarray(beta_B) * zf), 1.0)
    return direct + np.asarray(B_inf) * back_frac


def sfm_like_depth(
    clean: np.ndarray, range_m: np.ndarray, K: Dict[str, float], num_points: int, seed: Tuple[int, int]
) -> np.ndarray:
    """Sparse z-depth in millimetres (uint16, 0 = unknown) where structure-from-motion would
    have triangulated points: ``num_points`` pixels drawn among the most textured quarter of
    each view's object pixels (strong gradients of the clean image), none in open water.

    nerfstudio's depth images hold z-depth (along the optical axis), not range:
    ``z = range / |d_cam|`` with ``d_cam = ((u - cx)/fx, (v - cy)/fy, 1)``.
    """
    h, w = range_m.shape
    grey = clean.mean(axis=-1)
    gy, gx = np.gradient(grey)
    texture = np.hypot(gx, gy)
    hit = np.isfinite(range_m)
    candidates = np.flatnonzero(hit.ravel() & (texture.ravel() >= np.quantile(texture[hit], 0.75)))
    rng = np.random.default_rng(list(seed))
    chosen = rng.choice(candidates, size=min(num_points, len(candidates)), replace=False)
    v, u = np.divmod(chosen, w)
    norm = np.sqrt(((u + 0.5 - K["cx"]) / K["fl_x"]) ** 2 + ((v + 0.5 - K["cy"]) / K["fl_y"]) ** 2 + 1.0)
    depth_mm = np.zeros((h, w), dtype=np.uint16)
    depth_mm[v, u] = np.clip(np.round(range_m[v, u] / norm * 1000.0), 1, 65535).astype(np.uint16)
    return depth_mm


def write_png16_gray(path: Path, image: np.ndarray) -> None:
    """Write a uint16 single-channel PNG."""
    if not cv2.imwrite(str(path), np.ascontiguousarray(image.astype(np.uint16))):
        raise OSError(f"could not write {path}")


def _to_u16(img: np.ndarray) -> np.ndarray:
    return np.round(np.clip(img, 0.0, 1.0) * 65535.0).astype(np.uint16)


def _write_png16(path: Path, rgb: np.ndarray) -> None:
    """Write linear RGB float image in [0,1] as 16-bit PNG (cv2 expects BGR order)."""
    if not cv2.imwrite(str(path), np.ascontiguousarray(_to_u16(rgb)[..., ::-1])):
        raise OSError(f"could not write {path}")


def _render_view(
    scene: _Scene, c2w: np.ndarray, K: Dict[str, float], w: int, h: int, ss: int, medium: Dict[str, np.ndarray]
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view: I (h,w,3) and J (h,w,3) linear, range (h,w) float32 in metres.

    The medium is applied per sub-sample before averaging. The range is that of the
    pixel-centre ray; if the centre ray misses but another sub-sample hits an object (silhouette
    against open water), the smallest sub-sample range is used instead, so that ``range == inf``
    exactly when every sub-sample saw open water (and then ``I == B_inf`` exactly).
    """
    o = c2w[:3, 3]
    vv, uu = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    # sub-samples on a regular ss x ss grid inside each pixel (pixel centres at +0.5)
    offs = (np.arange(ss) + 0.5) / ss
    su = np.broadcast_to(uu[..., None, None] + offs[None, None, None, :], (h, w, ss, ss))
    sv = np.broadcast_to(vv[..., None, None] + offs[None, None, :, None], (h, w, ss, ss))
    d = _pixel_rays(c2w, K, su.ravel(), sv.ravel())
    J, t = scene.shade(o, d)
    I = apply_medium(J, t, medium["beta_D"], medium["beta_B"], medium["B_inf"])
    n = ss * ss
    I = I.reshape(h, w, n, 3).mean(axis=2)
    J = J.reshape(h, w, n, 3).mean(axis=2)
    t_sub = t.reshape(h, w, n)
    if ss % 2 == 1:  # the middle sub-sample is the pixel centre
        t_centre = t_sub[:, :, n // 2]
    else:
        dc = _pixel_rays(c2w, K, (uu + 0.5).ravel(), (vv + 0.5).ravel())
        t_centre = scene.trace(o, dc)[0].reshape(h, w)
    depth = np.where(np.isfinite(t_centre), t_centre, t_sub.min(axis=2))
    return I, J, depth.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Output
# ----------------------------------------------------------------------------------------------


def _check_output_dir(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise SystemExit(f"seathru-synth: output path {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise SystemExit(f"seathru-synth: output folder {out} exists and is not empty; pass --overwrite to replace it")


def _validate(config: SynthConfig) -> None:
    if config.preset not in PRESETS:
        raise SystemExit(f"seathru-synth: unknown preset {config.preset!r}; choose from {sorted(PRESETS)}")
    if config.width < 8 or config.height < 8:
        raise SystemExit("seathru-synth: --width and --height must be at least 8 pixels")
    if config.num_views < 2:
        raise SystemExit("seathru-synth: --num-views must be at least 2 (view 0 is held out)")
    if config.supersample < 1:
        raise SystemExit("seathru-synth: --supersample must be >= 1")


def generate(config: SynthConfig) -> Path:
    """Render the scene described by ``config`` into ``config.output_dir`` and return that path.

    Raises ``SystemExit`` (with a message naming the folder) if the folder exists and is
    non-empty and ``config.overwrite`` is False.
    """
    _validate(config)
    out = Path(config.output_dir).expanduser().absolute()
    _check_output_dir(out, config.overwrite)
    start = time.perf_counter()

    w, h, n_views, ss = config.width, config.height, config.num_views, config.supersample
    medium = {k: np.asarray(v, dtype=np.float64) for k, v in PRESETS[config.preset].items()}
    rng_scene = np.random.default_rng([config.seed, 1])
    rng_cams = np.random.default_rng([config.seed, 2])
    geometry = GEOMETRY.get(config.preset, Geometry())
    scene = _build_scene(rng_scene, geometry)
    poses = _make_poses(rng_cams, n_views, geometry)
    K = _intrinsics(w, h)

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        (tmp / "images").mkdir()
        (tmp / "ground_truth" / "clean").mkdir(parents=True)
        (tmp / "ground_truth" / "depth").mkdir(parents=True)
        if config.sfm_points_per_view > 0:
            (tmp / "depth").mkdir()
        frames = []
        names = []
        n_open = 0
        with Progress(
            TextColumn("[bold]seathru-synth[/] {task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=CONSOLE,
            transient=True,
        ) as progress:
            task = progress.add_task(f"{config.preset} {w}x{h}", total=n_views)
            # Views are independent; numpy releases the GIL, so two threads use both cores.
            # Results come back in view order, so the output does not depend on scheduling.
            render = lambda c2w: _render_view(scene, c2w, K, w, h, ss, medium)  # noqa: E731
            with ThreadPoolExecutor(max_workers=max(1, min(2, os.cpu_count() or 1))) as pool:
                results = pool.map(render, list(poses))
                for i, (I, J, depth) in enumerate(results):
                    stem = f"frame_{i:05d}"
                    name = f"images/{stem}.png"
                    _write_png16(tmp / name, I)
                    _write_png16(tmp / "ground_truth" / "clean" / f"{stem}.png", J)
                    np.save(tmp / "ground_truth" / "depth" / f"{stem}.npy", depth)
                    n_open += int(np.sum(~np.isfinite(depth)))
                    frame = {"file_path": name, "transform_matrix": poses[i].tolist()}
                    if config.sfm_points_per_view > 0:
                        frame["depth_file_path"] = f"depth/{stem}.png"
                        sparse = sfm_like_depth(J, depth, K, config.sfm_points_per_view, seed=(config.seed, i))
                        write_png16_gray(tmp / frame["depth_file_path"], sparse)
                    frames.append(frame)
                    names.append(name)
                    progress.advance(task)

        held = [names[i] for i in range(n_views) if i % HOLDOUT_EVERY == 0]
        train = [names[i] for i in range(n_views) if i % HOLDOUT_EVERY != 0]
        transforms = {
            "camera_model": "OPENCV",
            **K,
            "w": w,
            "h": h,
            "k1": 0.0,
            "k2": 0.0,
            "p1": 0.0,
            "p2": 0.0,
            "frames": frames,
            "train_filenames": train,
            "val_filenames": held,
            "test_filenames": held,
        }
        (tmp / "transforms.json").write_text(json.dumps(transforms, indent=2) + "\n")
        med = {
            "preset": config.preset,
            "beta_D": medium["beta_D"].tolist(),
            "beta_B": medium["beta_B"].tolist(),
            "B_inf": medium["B_inf"].tolist(),
            "units": "1/m",
            "world_units": "m",
            "color_space": "linear",
            "image_formation": "I = J*exp(-beta_D*z) + B_inf*(1-exp(-beta_B*z)), z = range (m)",
            "depth": "ground_truth/depth/*.npy: float32 range from camera centre along the pixel-centre ray, "
            "metres; inf = open water (I = B_inf, J = 0)",
            "images": "16-bit PNG, RGB order, value/65535 = linear radiance",
            "sfm_depth": "depth/*.png: sparse z-depth in millimetres at textured pixels (0 = unknown), "
            "like structure-from-motion points; nerfstudio's depth_file_path",
            "geometry": vars(geometry),
            "pose_convention": "nerfstudio/OpenGL camera-to-world (camera looks along -z, +y up)",
            "width": w,
            "height": h,
            "num_views": n_views,
            "seed": config.seed,
            "supersample": ss,
            "horizontal_fov_deg": HORIZONTAL_FOV_DEG,
            "holdout_every": HOLDOUT_EVERY,
            "open_water_fraction": n_open / float(n_views * w * h),
        }
        (tmp / "ground_truth" / "medium.json").write_text(json.dumps(med, indent=2) + "\n")

        # Swap into place (re-check: the folder may have appeared meanwhile).
        _check_output_dir(out, config.overwrite)
        trash: Optional[Path] = None
        if out.is_dir():
            if any(out.iterdir()):
                trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
                os.rename(out, trash / "old")
            else:
                out.rmdir()
        os.rename(tmp, out)
        if trash is not None:
            shutil.rmtree(trash, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise

    CONSOLE.print(
        f"seathru-synth: wrote {n_views} views ({w}x{h}, preset={config.preset}, seed={config.seed}) "
        f"to {out} in {time.perf_counter() - start:.1f}s"
    )
    return out


def entrypoint() -> None:
    """CLI entry point (``seathru-synth``)."""
    generate(tyro.cli(SynthConfig))


if __name__ == "__main__":
    entrypoint()
