"""The scene's vertical, from the training cameras: the axis along which the veil rises.

Light falls from above, so open water brightens looking up (:class:`~seathru_nerfstudio.
medium_field.SceneMedium`). "Up" is the direction of gravity, which the poses do not give
directly. nerfstudio's ``"up"`` orientation turns the cameras' *mean up vector* into ``+z``; a rig
pitched down by ``θ`` (a diver filming a reef: 10–45°) leaves that ``+z`` tilted by ``θ`` from the
vertical, so a ray looking level reads as looking up by ``sin θ``.

A camera held level (no roll) has its *right* vector horizontal whatever its pitch. So the
vertical is the unit ``v`` most nearly orthogonal to every camera's right vector ``r_i``:

    v = argmin_{|v| = 1}  mean_i (v·r_i)² + μ (1 - (v·ū)²)

with ``ū`` the cameras' mean up vector. The first term fixes ``v`` wherever the cameras face more
than one way; the second, weighed by :data:`MEAN_UP_WEIGHT`, picks among the directions the first
leaves free when they all face one way (``v = ū`` projected off the common right vector, the mean
up without its roll), and otherwise moves ``v`` by about ``μ / λ`` of its angle to ``ū`` (``λ``: the
second eigenvalue of ``mean r rᵀ``). The minimiser is the eigenvector of the smallest eigenvalue
of ``mean_i r_i r_iᵀ - μ ū ūᵀ``, signed to agree with ``ū``.

On the path-traced presets (cameras pitched about 10° down, their yaws spread by about ±6°, poses
from our SfM) this lands 0.7–4.7° from the true vertical, where the mean up vector is 9.9–11.0° off
(docs/history.md, 2026-11-29 (the scene's vertical)).
Units: directions are unit vectors in nerfstudio's scene frame (OpenGL camera axes: ``x`` right,
``y`` up, ``z`` backwards).
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

MEAN_UP_WEIGHT = 1e-3
"""``μ``: the mean up vector's weight, about a camera roll of 1.8° (``sin² 1.8° ≈ 1e-3``), so it only
decides where the right vectors leave the vertical free."""


def scene_vertical(camera_to_worlds: Float[Tensor, "N 3 4"]) -> Float[Tensor, "3"]:
    """The unit vertical (up) of the scene frame from cameras held level (module docstring);
    ``+z`` when there is no camera or their up vectors cancel. float64."""
    if camera_to_worlds.shape[0] == 0:
        return torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    rotations = camera_to_worlds[:, :3, :3].double()
    rights = torch.nn.functional.normalize(rotations[:, :, 0], dim=-1)
    mean_up = rotations[:, :, 1].mean(dim=0)
    if float(mean_up.norm()) < 1e-6:
        return torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    mean_up = mean_up / mean_up.norm()
    scatter = rights.T @ rights / rights.shape[0] - MEAN_UP_WEIGHT * torch.outer(mean_up, mean_up)
    _, vectors = torch.linalg.eigh(scatter)
    vertical = vectors[:, 0]
    return vertical if float(vertical @ mean_up) >= 0 else -vertical


def level_direction(vertical: Float[Tensor, "3"]) -> Float[Tensor, "3"]:
    """A unit direction orthogonal to ``vertical`` (unit): scene ``+x`` made level, or ``+y`` where
    ``vertical`` is nearly ``±x``."""
    axis = torch.zeros_like(vertical)
    axis[0 if abs(float(vertical[0])) < 0.9 else 1] = 1.0
    level = axis - (axis @ vertical) * vertical
    return level / level.norm()


def level_frame(vertical: Float[Tensor, "3"]) -> Float[Tensor, "3 2"]:
    """Two unit level axes of ``vertical`` (unit) as columns: ``e1`` = :func:`level_direction`,
    ``e2 = vertical × e1``, so that ``(e1, e2, vertical)`` is right-handed. In ``vertical``'s dtype."""
    first = level_direction(vertical)
    return torch.stack([first, torch.linalg.cross(vertical, first)], dim=1)
