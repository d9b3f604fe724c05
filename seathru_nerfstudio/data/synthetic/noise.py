"""Procedural noise for the synthetic scene's textures: deterministic integer hashing of
lattice cells with wrapping uint32 arithmetic, no global random state: the same points and
salt give the same values on every run."""

from __future__ import annotations

import numpy as np

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


def cells(q: np.ndarray) -> np.ndarray:
    """Integer lattice cell of points (N, 3) as wrapping uint32 (N, 3)."""
    return np.floor(q).astype(np.int32).view(np.uint32)


def hash01(c: np.ndarray, salt: int) -> np.ndarray:
    """Hash uint32 lattice cells (N, 3) to float32 in [0, 1) (deterministic, wraps mod 2^32)."""
    h = (c[:, 0] * _PX) ^ (c[:, 1] * _PY) ^ (c[:, 2] * _PZ) ^ _U32(salt & 0xFFFFFFFF)
    return _finalize(h)


def value_noise(q: np.ndarray, salt: int) -> np.ndarray:
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


def fbm(q: np.ndarray, salt: int, octaves: int, lacunarity: float = 2.13) -> np.ndarray:
    """Fractal value noise in [0, 1]; octaves use non-integer frequency ratios and offsets so
    the result has no visible period."""
    total = np.zeros(len(q))
    amp, norm, freq = 1.0, 0.0, 1.0
    for o in range(octaves):
        shift = np.array([17.31, 5.77, 11.13]) * (o + 1)
        total += amp * value_noise(q * freq + shift, salt + 1013 * o)
        norm += amp
        amp *= 0.6
        freq *= lacunarity
    return total / norm


def hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectorised HSV -> RGB; h in turns (wraps), s and v in [0, 1]. Returns (N, 3)."""
    h6 = (h % 1.0) * 6.0
    k = (np.array([5.0, 3.0, 1.0])[None, :] + h6[:, None]) % 6.0
    return v[:, None] - v[:, None] * s[:, None] * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)

