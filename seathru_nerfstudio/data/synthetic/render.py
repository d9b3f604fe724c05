"""Image formation of the synthetic scene: the medium presets, the SeaThru model, a rendered
view (supersampled, the medium applied per ray) and the sparse depth SfM would have given."""

from __future__ import annotations

from typing import Dict, List, Literal, Tuple

import numpy as np

from seathru_nerfstudio.data.synthetic.cameras import pixel_rays
from seathru_nerfstudio.data.synthetic.scene import Scene

PresetName = Literal["water", "turbid", "fog", "none"]

#: Medium presets: attenuation beta_D (1/m), backscatter beta_B (1/m), veiling light B_inf
#: (linear RGB). ``water`` is the paper's underwater *Fern* simulation (Sec. 5).
PRESETS: Dict[str, Dict[str, List[float]]] = {
    "water": {"beta_D": [1.3, 1.2, 0.9], "beta_B": [0.95, 0.85, 0.7], "B_inf": [0.07, 0.2, 0.39]},
    "turbid": {"beta_D": [0.62, 0.38, 0.46], "beta_B": [0.48, 0.32, 0.38], "B_inf": [0.04, 0.26, 0.18]},
    "fog": {"beta_D": [1.2, 1.2, 1.2], "beta_B": [1.2, 1.2, 1.2], "B_inf": [0.6, 0.6, 0.6]},
    "none": {"beta_D": [0.0, 0.0, 0.0], "beta_B": [0.0, 0.0, 0.0], "B_inf": [0.0, 0.0, 0.0]},
}


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


def render_view(
    scene: Scene, c2w: np.ndarray, K: Dict[str, float], w: int, h: int, ss: int, medium: Dict[str, np.ndarray]
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
    d = pixel_rays(c2w, K, su.ravel(), sv.ravel())
    J, t = scene.shade(o, d)
    I = apply_medium(J, t, medium["beta_D"], medium["beta_B"], medium["B_inf"])
    n = ss * ss
    I = I.reshape(h, w, n, 3).mean(axis=2)
    J = J.reshape(h, w, n, 3).mean(axis=2)
    t_sub = t.reshape(h, w, n)
    if ss % 2 == 1:  # the middle sub-sample is the pixel centre
        t_centre = t_sub[:, :, n // 2]
    else:
        dc = pixel_rays(c2w, K, (uu + 0.5).ravel(), (vv + 0.5).ravel())
        t_centre = scene.trace(o, dc)[0].reshape(h, w)
    depth = np.where(np.isfinite(t_centre), t_centre, t_sub.min(axis=2))
    return I, J, depth.astype(np.float32)


