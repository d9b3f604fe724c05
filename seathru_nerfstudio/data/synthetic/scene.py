"""The synthetic scene: a textured back wall with an irregular top edge, a ground plane, and a
few spheres and boxes, in metres (world +y up; the cameras sit near z = 0 looking towards -z).

Everything is analytic: rays are intersected in closed form and shaded Lambertian with an
ambient term and hard shadows cast by the objects. Primitives are immutable once built;
:meth:`Wall.__post_init__` tabulates the wall's top edge, so rendering threads only read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import ClassVar, Dict, Tuple, Union

import numpy as np

from seathru_nerfstudio.data.synthetic.noise import cells, fbm, hash01, hsv_to_rgb, value_noise

WALL_Z = -1.85
GROUND_Y = -0.7
WALL_TOP_Y = 0.22
EPS = 1e-6
"""Hits closer than this along a ray are ignored (self-intersection)."""
WALL_TOP_KNOT = 0.002
"""Spacing (m) of the knots of the wall's piecewise-linear top edge."""


@dataclass(frozen=True)
class Geometry:
    """How a preset's scene is laid out, relative to the base scene (objects 0.76-2.6 m away)."""

    scene_scale: float = 1.0
    """Every primitive's position, size and texture scaled by this about the rig's origin."""
    near_scale: float = 1.0
    """The same for the nearest sphere, so that a scaled scene still has something close."""
    rig_scale: float = 1.0
    """Camera rig extent scaled by this."""
    rig_depth: float = 0.0
    """Camera centres also spread over this many metres along the rig's axis, behind its plane
    (a capture that swims toward or away from the scene). The attenuation is determined by how
    much a surface point's range differs between the views that see it, which a flat rig keeps small."""


#: ``turbid``: green coastal water, a scene 3.5x deeper (objects about 1 to 8 m away).
GEOMETRY: Dict[str, Geometry] = {"turbid": Geometry(scene_scale=3.5, near_scale=1.4, rig_scale=1.5)}


@dataclass(frozen=True)
class Texture:
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
        low = value_noise(q / 0.4, self.salt + 1)
        hue = self.hue + self.hue_spread * (low - 0.5)
        sat = np.clip(self.sat * (0.6 + 0.8 * (1.0 - low)), 0.0, 1.0)
        fine = fbm(q / self.noise_cell, self.salt + 2, 3)
        rgb = hsv_to_rgb(hue, sat, 0.25 + 0.75 * fine)
        # Noise-warped 3D checkers (cell size varies locally -> not periodic).
        mid = value_noise(q / 0.2 + 7.7, self.salt + 4) - 0.5
        cq = np.floor((q + (0.6 * self.checker_cell) * mid[:, None]) / self.checker_cell).astype(np.int64)
        chk = ((cq[:, 0] + cq[:, 1] + cq[:, 2]) & 1).astype(np.float64)[:, None]
        rgb = rgb * (1.0 - self.checker_weight * chk) + self.checker_weight * chk * self.checker_rgb
        # Wavy stripes along a random direction, darkening.
        phase = q @ self.stripe_dir / self.stripe_period + 2.5 * mid
        stripe = (np.sin(2.0 * np.pi * phase) > 0.3)[:, None]
        rgb = np.where(stripe, rgb * (1.0 - self.stripe_weight), rgb)
        # Random coloured blobs: at most one ball per jittered cell (solid Worley-like spots).
        cell = q / self.blob_cell
        ci = cells(cell)
        local = cell - np.floor(cell)
        s = self.salt + 100
        present = hash01(ci, s) < self.blob_prob
        rad = 0.15 + 0.2 * hash01(ci, s + 1)
        d2 = np.zeros(n)
        for k in range(3):
            ck = rad + (1.0 - 2.0 * rad) * hash01(ci, s + 2 + k)
            d2 += (local[:, k] - ck) ** 2
        inside = present & (d2 < rad**2)
        if np.any(inside):
            cj = ci[inside]
            bh = hash01(cj, s + 10)
            bv = hash01(cj, s + 11)
            bval = np.where(bv < 0.3, 0.12 + 0.1 * bv, 0.65 + 0.3 * bv)
            rgb[inside] = hsv_to_rgb(bh, np.full(len(cj), 0.85), bval)
        return np.clip(rgb, 0.1, 0.95)


def random_texture(rng: np.random.Generator, salt: int) -> Texture:
    sd = rng.normal(size=3)
    return Texture(
        salt=salt,
        hue=float(rng.uniform()),
        hue_spread=float(rng.uniform(0.3, 0.8)),
        sat=float(rng.uniform(0.45, 0.85)),
        noise_cell=float(rng.uniform(0.035, 0.06)),
        checker_cell=float(rng.uniform(0.05, 0.12)),
        checker_weight=float(rng.uniform(0.25, 0.5)),
        checker_rgb=hsv_to_rgb(np.array([rng.uniform()]), np.array([0.7]), np.array([0.85]))[0],
        stripe_dir=sd / np.linalg.norm(sd),
        stripe_period=float(rng.uniform(0.05, 0.11)),
        stripe_weight=float(rng.uniform(0.2, 0.45)),
        blob_cell=float(rng.uniform(0.09, 0.15)),
        blob_prob=float(rng.uniform(0.35, 0.6)),
        offset=rng.uniform(-50.0, 50.0, size=3),
    )


# Every primitive: ``intersect(o, d)`` -> distance t along unit rays ``o + t d`` to the first hit
# in front (inf on a miss), ``o`` one origin (3,) shared by all rays or per-ray origins (N, 3);
# ``normal(p)`` -> outward unit normals (N, 3) at surface points; ``scaled(factor)`` -> the
# primitive scaled about the origin (it looks the same from there, ``factor`` times farther
# away); ``texture`` evaluated at ``p / tex_scale``; ``casts_shadow``.


def _bounding_sphere(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float):
    """Rays that hit the sphere (centre, radius) in front: their indices ``cand``, and for all
    rays ``oc = o - centre``, ``b = d . oc`` and the discriminant."""
    oc = o - centre
    b = d @ oc if oc.ndim == 1 else np.einsum("ij,ij->i", d, oc)
    c = (oc @ oc if oc.ndim == 1 else np.einsum("ij,ij->i", oc, oc)) - radius**2
    disc = b * b - c
    cand = np.flatnonzero((disc > 0) & (-b + np.sqrt(np.maximum(disc, 0.0)) > EPS))
    return cand, oc, b, disc


@dataclass(frozen=True)
class Sphere:
    texture: Texture
    centre: np.ndarray
    radius: float
    tex_scale: float = 1.0
    casts_shadow: ClassVar[bool] = True

    def scaled(self, factor: float) -> "Sphere":
        return replace(self, centre=self.centre * factor, radius=self.radius * factor, tex_scale=self.tex_scale * factor)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        t = np.full(len(d), np.inf)
        cand, _, b, disc = _bounding_sphere(o, d, self.centre, self.radius)
        sq = np.sqrt(disc[cand])
        t0 = -b[cand] - sq
        t[cand] = np.where(t0 > EPS, t0, -b[cand] + sq)
        return t

    def normal(self, p: np.ndarray) -> np.ndarray:
        return (p - self.centre) / self.radius


@dataclass(frozen=True)
class Box:
    """Oriented box: ``centre``, half extents ``half`` and rotation ``rot`` (local -> world)."""

    texture: Texture
    centre: np.ndarray
    half: np.ndarray
    rot: np.ndarray
    tex_scale: float = 1.0
    casts_shadow: ClassVar[bool] = True

    def scaled(self, factor: float) -> "Box":
        return replace(self, centre=self.centre * factor, half=self.half * factor, tex_scale=self.tex_scale * factor)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        t = np.full(len(d), np.inf)
        cand, oc, _, _ = _bounding_sphere(o, d, self.centre, float(np.linalg.norm(self.half)))
        if len(cand) == 0:
            return t
        # slab test in the box frame on bounding-sphere candidates only
        ol = (oc if oc.ndim == 1 else oc[cand]) @ self.rot  # world -> local
        dl = d[cand] @ self.rot
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dl
            ta = (-self.half - ol) * inv
            tb = (self.half - ol) * inv
        tnear = np.max(np.minimum(ta, tb), axis=1)
        tfar = np.min(np.maximum(ta, tb), axis=1)
        tt = np.where(tnear > EPS, tnear, tfar)
        ok = (tnear <= tfar) & (tfar > EPS) & np.isfinite(tt)
        t[cand[ok]] = tt[ok]
        return t

    def normal(self, p: np.ndarray) -> np.ndarray:
        pl = (p - self.centre) @ self.rot
        rel = np.abs(pl) / self.half
        axis = np.argmax(rel, axis=1)
        nl = np.zeros_like(pl)
        rows = np.arange(len(p))
        nl[rows, axis] = np.sign(pl[rows, axis])
        return nl @ self.rot.T


def _plane_hits(o: np.ndarray, d: np.ndarray, axis: int, plane: float):
    """Rays that cross the plane ``x[axis] == plane`` in front: indices, distances, points."""
    o_ax = o[axis] if o.ndim == 1 else o[:, axis]
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = (plane - o_ax) / d[:, axis]
    idx = np.flatnonzero(np.isfinite(tt) & (tt > EPS))
    p = (o if o.ndim == 1 else o[idx]) + tt[idx, None] * d[idx]
    return idx, tt, p


def _plane_normal(p: np.ndarray, axis: int) -> np.ndarray:
    nrm = np.zeros_like(p)
    nrm[:, axis] = 1.0
    return nrm


@dataclass(frozen=True)
class Ground:
    """The plane y = ``plane``, for x in ``bounds[0:2]`` and z in ``bounds[2:4]``."""

    texture: Texture
    plane: float
    bounds: Tuple[float, float, float, float]
    tex_scale: float = 1.0
    casts_shadow: ClassVar[bool] = False

    def scaled(self, factor: float) -> "Ground":
        bounds = tuple(b * factor for b in self.bounds)
        return replace(self, plane=self.plane * factor, bounds=bounds, tex_scale=self.tex_scale * factor)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        t = np.full(len(d), np.inf)
        idx, tt, p = _plane_hits(o, d, 1, self.plane)
        a0, a1, b0, b1 = self.bounds
        inb = (p[:, 0] >= a0) & (p[:, 0] <= a1) & (p[:, 2] >= b0) & (p[:, 2] <= b1)
        t[idx[inb]] = tt[idx[inb]]
        return t

    def normal(self, p: np.ndarray) -> np.ndarray:
        return _plane_normal(p, 1)


@dataclass(frozen=True)
class Wall:
    """The plane z = ``plane``, for x in ``bounds[0:2]`` and y from ``bounds[2]`` up to an
    irregular top edge: ``bounds[3]`` plus fractal bumps of amplitude ``top_amp``, tabulated
    at construction (piecewise linear, knots every :data:`WALL_TOP_KNOT` metres)."""

    texture: Texture
    plane: float
    bounds: Tuple[float, float, float, float]
    top_amp: float
    tex_scale: float = 1.0
    casts_shadow: ClassVar[bool] = False
    top_x: np.ndarray = field(init=False, repr=False, compare=False)
    top_y: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        x0, x1 = self.bounds[0], self.bounds[1]
        xs = np.linspace(x0, x1, int(round((x1 - x0) / WALL_TOP_KNOT)) + 1)
        q = np.stack([xs / (0.3 * self.tex_scale), np.zeros_like(xs), np.zeros_like(xs)], 1)
        bumps = fbm(q, self.texture.salt + 77, 3).astype(np.float64) - 0.5
        object.__setattr__(self, "top_x", xs)  # a frozen dataclass's derived fields
        object.__setattr__(self, "top_y", self.bounds[3] + 2.0 * self.top_amp * bumps)

    def scaled(self, factor: float) -> "Wall":
        bounds = tuple(b * factor for b in self.bounds)
        return replace(
            self, plane=self.plane * factor, bounds=bounds, top_amp=self.top_amp * factor, tex_scale=self.tex_scale * factor
        )

    def top(self, x: np.ndarray) -> np.ndarray:
        """Height (m) of the top edge at world x."""
        return np.interp(x, self.top_x, self.top_y)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        t = np.full(len(d), np.inf)
        idx, tt, p = _plane_hits(o, d, 2, self.plane)
        a0, a1, b0, b1 = self.bounds
        inb = (p[:, 0] >= a0) & (p[:, 0] <= a1) & (p[:, 1] >= b0) & (p[:, 1] <= b1 + self.top_amp)
        inb[inb] &= p[inb, 1] <= self.top(p[inb, 0])
        t[idx[inb]] = tt[idx[inb]]
        return t

    def normal(self, p: np.ndarray) -> np.ndarray:
        return _plane_normal(p, 2)


Primitive = Union[Sphere, Box, Ground, Wall]


@dataclass(frozen=True)
class Scene:
    prims: Tuple[Primitive, ...]
    light_dir: np.ndarray
    """Unit vector towards the light."""
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
            if prim.casts_shadow:
                blocked |= np.isfinite(prim.intersect(ps, ls))
        ndl[lit_idx[blocked]] = 0.0
        J[hit] = alb * (self.ambient + (1.0 - self.ambient) * ndl)[:, None]
        return J, t


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


NEAR_SPHERE = 2
"""Index of the nearest sphere in :func:`build_scene`'s list."""


def build_scene(rng: np.random.Generator, geometry: Geometry = Geometry()) -> Scene:
    """The scene drawn from ``rng``: wall at z=-1.85, ground at y=-0.7, open water above the
    wall's irregular top edge (~0.22 m); all of it times ``geometry``'s scales."""
    salt = int(rng.integers(0, 2**31))
    tex = lambda k: random_texture(rng, salt + 7919 * k)  # noqa: E731
    j = lambda s: rng.uniform(-s, s, size=3)  # noqa: E731
    prims = [
        Wall(tex(0), plane=WALL_Z, bounds=(-3.0, 3.0, GROUND_Y, WALL_TOP_Y), top_amp=0.07),
        Ground(tex(1), plane=GROUND_Y, bounds=(-3.0, 3.0, WALL_Z, -0.2)),
        # near sphere (~0.7 m from the rig)
        Sphere(tex(2), centre=np.array([-0.33, -0.3, -0.88]) + j(0.03), radius=0.17 + rng.uniform(-0.015, 0.015)),
        # mid sphere resting near the ground
        Sphere(tex(3), centre=np.array([0.42, -0.45, -1.4]) + j(0.05), radius=0.24 + rng.uniform(-0.03, 0.03)),
        # rotated box on the ground
        Box(
            tex(4),
            centre=np.array([-0.05, -0.5, -1.3]) + j(0.05) * np.array([1, 0, 1]),
            half=np.array([0.17, 0.2, 0.14]),
            rot=_rot_y(rng.uniform(0.3, 0.9)),
        ),
        # tall pillar, rising above the wall into open water
        Box(
            tex(5),
            centre=np.array([0.15, -0.15, -1.62]) + j(0.05) * np.array([1, 0, 1]),
            half=np.array([0.07, 0.55, 0.07]),
            rot=_rot_y(rng.uniform(0.0, 1.5)) @ _rot_x(rng.uniform(-0.08, 0.08)),
        ),
        # far sphere, partly above the wall
        Sphere(tex(6), centre=np.array([-0.68, 0.05, -1.65]) + j(0.05), radius=0.18 + rng.uniform(-0.02, 0.02)),
        # far box
        Box(
            tex(7),
            centre=np.array([0.8, -0.1, -1.62]) + j(0.05),
            half=np.array([0.14, 0.14, 0.14]),
            rot=_rot_y(rng.uniform(0, 1.5)) @ _rot_x(rng.uniform(0, 1.5)),
        ),
    ]
    scales = [geometry.near_scale if k == NEAR_SPHERE else geometry.scene_scale for k in range(len(prims))]
    light = np.array([-0.4, 0.8, 0.45])
    return Scene(
        prims=tuple(prim if s == 1.0 else prim.scaled(s) for prim, s in zip(prims, scales)),
        light_dir=light / np.linalg.norm(light),
    )
