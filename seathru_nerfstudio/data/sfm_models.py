"""Which of the incremental mapper's models to keep, and how far two of them disagree.

A model from another initial pair may register the same images and still place them
otherwise: the mapper is a local optimiser, and a forward-facing capture with short baselines
has a flattened solution (the depth scaled down, the cameras turned) that bundle adjustment
converges to as well. These functions rank the models and measure the disagreement, independent
of each model's arbitrary similarity (gauge).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:  # not imported here: pycolmap must load after OpenCV (see data/sfm.py)
    import pycolmap


def num_observations(reconstruction: pycolmap.Reconstruction) -> int:
    """Feature observations the model's 3D points explain (the summed length of their tracks):
    what its bundle adjustment kept as inliers (a count)."""
    return int(sum(point.track.length() for point in reconstruction.points3D.values()))


def complete_starts(registered_counts: Sequence[int], num_images: int, fraction: float) -> int:
    """How many of the mapper's starts, given the images each registered, hold at least ``fraction``
    of ``num_images``."""
    return sum(count >= fraction * num_images for count in registered_counts)


def model_rank(reconstruction: pycolmap.Reconstruction) -> tuple[int, int]:
    """Which of two mapper models is better: more registered images, then more observations."""
    return reconstruction.num_reg_images(), num_observations(reconstruction)


def rotation_angle_deg(rotation: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Angle of rotation matrices (..., 3, 3), degrees: ``θ = 2 arcsin(‖R − I‖_F / (2√2))``, exact
    for a rotation and accurate near 0, where ``arccos((tr R − 1) / 2)`` loses half the digits."""
    chord = np.linalg.norm(rotation - np.eye(3), axis=(-2, -1)) / (2.0 * np.sqrt(2.0))
    return np.degrees(2.0 * np.arcsin(np.clip(chord, 0.0, 1.0)))


def rotation_disagreement_deg(rotations_a: npt.NDArray[np.float64], rotations_b: npt.NDArray[np.float64]) -> float:
    """How far two reconstructions of the same images orient their cameras apart, degrees.

    ``rotations_a``, ``rotations_b``: (N, 3, 3) world-to-camera rotations of the same N images.
    A reconstruction is known up to a similarity of the world (the gauge), which turns every
    camera of one by the same ``G``: ``R_b,i = R_a,i G``. ``G`` is taken as the rotation nearest
    ``Σ_i R_a,iᵀ R_b,i`` (SVD), and the result is the median over i of the angle of
    ``R_a,iᵀ R_b,i Gᵀ`` (:func:`rotation_angle_deg`).
    """
    relative = np.einsum("nji,njk->nik", rotations_a, rotations_b)  # R_a,i^T R_b,i
    u, _, vt = np.linalg.svd(relative.sum(axis=0))
    gauge = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    return float(np.median(rotation_angle_deg(relative @ gauge.T)))


def models_disagreement_deg(a: pycolmap.Reconstruction, b: pycolmap.Reconstruction) -> float | None:
    """:func:`rotation_disagreement_deg` of two models over the images both registered (by
    name; ``None`` under 3)."""
    rotations = []
    for model in (a, b):
        rotations.append({model.images[i].name: model.images[i].cam_from_world().rotation.matrix() for i in model.reg_image_ids()})
    shared = sorted(set(rotations[0]) & set(rotations[1]))
    if len(shared) < 3:
        return None
    return rotation_disagreement_deg(*(np.array([r[n] for n in shared]) for r in rotations))
