"""Does a path-traced scene's backscatter depend on the direction a surface is seen in? (An oracle:
the true range, the true J and the true poses; seconds of CPU per scene.)

For every object pixel of the training views of a ``seathru-pathtrace`` scene, the true
backscatter is ``B = I − J e^{−β_D z}`` (``J`` from ``ground_truth/clean``, ``z`` from
``ground_truth/depth``, ``β_D = σ_t``). Printed per scene:

* ``B`` over the best-fit constant medium's ``B∞ (1 − e^{−β_B z})`` (``ground_truth/medium.json``),
  by quartile of the ray's ``u = sin(elevation)`` (world +y) and by range;
* per channel, the best constant medium and a medium whose rate depends on the direction as single
  scattering of light that falls with depth predicts, ``B = A / c(u) (1 − e^{−c(u) z})`` with
  ``c(u) = β − K u``: the slope at short range ``A`` is the same in every direction, and only the
  asymptote ``A / c(u)`` rises looking up. Their residuals say whether the surfaces see a veil
  that changes with elevation;
* the open water's colour by quintile of ``u``, and its mean against what the directional medium
  fitted to the surfaces predicts there.

    .venv/bin/python scripts/probe_elevation.py outputs/pathtraced/coastal [more scenes]
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

RANGE_BINS_M = (0.0, 2.0, 3.5, 5.0, 7.0, 10.0, 30.0)
MIN_PIXELS = 200


def training_pixels(scene: Path):
    """``(I, J, z, u)`` over every pixel of the training views: linear colours (N, 3), range (m; inf
    on open water) and the up component of the pixel-centre ray's unit direction."""
    from seathru_nerfstudio.data.linear_images import read_linear_image, read_range_map
    from seathru_nerfstudio.data.pathtrace.presets import HOLDOUT_EVERY, PRESETS
    from seathru_nerfstudio.data.pathtrace.scene import make_layout
    from seathru_nerfstudio.data.synthetic.cameras import HORIZONTAL_FOV_DEG

    options = json.loads((scene / "scene.json").read_text())["options"]
    poses = make_layout(options["seed"], options["num_views"], PRESETS[options["preset"]]).poses
    width, height = options["width"], options["height"]
    focal = (width / 2) / math.tan(math.radians(HORIZONTAL_FOV_DEG / 2))
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    camera_rays = np.stack([(u - width / 2) / focal, -(v - height / 2) / focal, -np.ones_like(u)], axis=-1)  # OpenGL
    camera_rays /= np.linalg.norm(camera_rays, axis=-1, keepdims=True)
    parts = []
    for k in range(options["num_views"]):
        if k % HOLDOUT_EVERY == 0:
            continue
        name = f"frame_{k:05d}"
        image = read_linear_image(scene / "images" / f"{name}.png").reshape(-1, 3)
        clean = read_linear_image(scene / "ground_truth" / "clean" / f"{name}.png").reshape(-1, 3)
        ranges = read_range_map(scene / "ground_truth" / "depth" / f"{name}.npy").reshape(-1)
        up = (camera_rays @ poses[k][:3, :3].T)[..., 1].reshape(-1)
        parts.append((image, clean, ranges, up))
    return tuple(np.concatenate(arrays).astype(np.float64) for arrays in zip(*parts))


def probe(scene: Path) -> None:
    truth = json.loads((scene / "ground_truth" / "medium.json").read_text())
    beta_d, beta_b, veil = (np.asarray(truth[k]) for k in ("beta_D", "beta_B", "B_inf"))
    image, clean, ranges, up = training_pixels(scene)
    surface, open_water = np.isfinite(ranges), ~np.isfinite(ranges)
    z, u = ranges[surface], up[surface]
    backscatter = image[surface] - clean[surface] * np.exp(-beta_d * z[:, None])
    print(f"\n== {scene}: {surface.sum()} surface pixels, u {np.percentile(u, [1, 50, 99]).round(3)}; "
          f"{open_water.sum()} open-water pixels, u {np.percentile(up[open_water], [1, 50, 99]).round(3)}")
    print("true backscatter / best-fit constant medium (R/G/B), by u quartile (rows) and range (columns, m):")
    print("  " + " ".join(f"{a:>5.1f}-{b:<5.1f}   " for a, b in zip(RANGE_BINS_M, RANGE_BINS_M[1:])))
    edges = np.quantile(u, [0, 0.25, 0.5, 0.75, 1])
    for low, high in zip(edges, edges[1:]):
        cells = []
        for near, far in zip(RANGE_BINS_M, RANGE_BINS_M[1:]):
            cell = (u >= low) & (u <= high) & (z >= near) & (z < far)
            if cell.sum() < MIN_PIXELS:
                cells.append("    --        ")
                continue
            ratio = backscatter[cell].mean(0) / (veil * -np.expm1(-beta_b * z[cell, None])).mean(0)
            cells.append("/".join(f"{r:.2f}" for r in ratio) + "  ")
        print(f"  u {low:+.2f}..{high:+.2f}: " + " ".join(cells))
    for c, name in enumerate("RGB"):
        observed = backscatter[:, c]
        constant = least_squares(lambda p: p[0] * -np.expm1(-p[1] * z) - observed, [veil[c], beta_b[c]], bounds=([0, 1e-4], [2, 5]))

        def directional_residual(p):
            rate = np.maximum(p[1] - p[2] * u, 1e-4)
            return p[0] / rate * -np.expm1(-rate * z) - observed

        directional = least_squares(directional_residual, [veil[c] * beta_b[c], beta_b[c], 0.0], bounds=([0, 1e-4, -5], [2, 5, 5]))
        slope, rate, fall = directional.x
        predicted_open = (slope / np.maximum(rate - fall * up[open_water], 1e-4)).mean()
        print(
            f"  {name}: constant B_inf {constant.x[0]:.4f} beta_B {constant.x[1]:.4f} rms {np.sqrt(np.mean(constant.fun ** 2)):.5f} | "
            f"directional A {slope:.4f} beta {rate:.4f} K {fall:+.4f} rms {np.sqrt(np.mean(directional.fun ** 2)):.5f} | "
            f"open water {image[open_water, c].mean():.4f}, directional predicts {predicted_open:.4f}"
        )
    print("open water's colour by u quintile:")
    edges = np.quantile(up[open_water], np.linspace(0, 1, 6))
    for low, high in zip(edges, edges[1:]):
        band = open_water & (up >= low) & (up <= high)
        print(f"  u {low:+.3f}..{high:+.3f}: {' '.join(f'{x:.4f}' for x in image[band].mean(0))}  (/ best-fit B_inf {' '.join(f'{x:.2f}' for x in image[band].mean(0) / veil)})")


if __name__ == "__main__":
    for path in sys.argv[1:]:
        probe(Path(path))
