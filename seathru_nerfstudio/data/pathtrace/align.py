"""Aligning structure-from-motion poses to the true ones with a similarity (Umeyama 1991).

SfM recovers the cameras up to a similarity (scale, rotation, translation). To compare its
frames with the rendered ground truth (range in metres, J), the recovered camera centres ``c``
are mapped onto the true ones ``t`` by the least-squares similarity::

    min_{s, R, T}  sum_i | t_i - (s R c_i + T) |^2

(Umeyama, "Least-squares estimation of transformation parameters between two point patterns",
PAMI 1991: SVD of the cross-covariance, with the reflection fix). The poses keep their own
rotations (only rotated by ``R``), so the registered geometry, not the truth, is what a method
sees; the sparse depths scale by ``s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass
class Similarity:
    scale: float
    rotation: npt.NDArray[np.float64]
    """(3, 3)"""
    translation: npt.NDArray[np.float64]
    """(3,)"""

    def apply_points(self, points: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """(N, 3) -> (N, 3): ``s R p + T``."""
        return self.scale * points @ self.rotation.T + self.translation

    def apply_pose(self, c2w: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """A (3 or 4, 4) camera-to-world with orthonormal rotation -> the same camera in the
        target frame (4, 4): rotation ``R @ R_c2w``, centre ``s R c + T``."""
        out = np.eye(4)
        out[:3, :3] = self.rotation @ c2w[:3, :3]
        out[:3, 3] = self.apply_points(c2w[None, :3, 3])[0]
        return out


def umeyama(source: npt.NDArray[np.float64], target: npt.NDArray[np.float64]) -> Similarity:
    """The similarity mapping ``source`` (N, 3) onto ``target`` (N, 3) in least squares; N >= 3
    points not all on one line. Raises ValueError otherwise."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"umeyama needs two (N>=3, 3) arrays of the same shape, got {source.shape} and {target.shape}")
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    var_s = float((xs**2).sum() / len(source))
    if var_s <= 1e-18:
        raise ValueError("the source points coincide: no scale or rotation can be recovered")
    u, d, vt = np.linalg.svd(xt.T @ xs / len(source))
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[-1] = -1.0
    rotation = u @ np.diag(sign) @ vt
    scale = float((d * sign).sum() / var_s)
    return Similarity(scale, rotation, mu_t - scale * rotation @ mu_s)


def rotation_error_deg(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> float:
    """Angle (degrees) of the rotation between the (3, 3) rotation parts of two poses."""
    from seathru_nerfstudio.data.sfm_models import rotation_angle_deg

    return float(rotation_angle_deg(a[:3, :3].T @ b[:3, :3]))
