"""Colour transforms shared by the display layer (:mod:`seathru_nerfstudio.viewer`) and the
metrics (:mod:`seathru_nerfstudio.metrics`): the sRGB transfer function, IEC 61966-2-1.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def linear_to_srgb(x: Float[Tensor, "*shape"]) -> Float[Tensor, "*shape"]:
    """sRGB encoding of linear values, clamped to ``[0, 1]`` first:
    ``12.92 x`` for ``x <= 0.0031308``, else ``1.055 x^(1/2.4) - 0.055``."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055)


def srgb_to_linear(x: Float[Tensor, "*shape"]) -> Float[Tensor, "*shape"]:
    """Inverse of :func:`linear_to_srgb`: ``x / 12.92`` for ``x <= 0.04045``, else
    ``((x + 0.055) / 1.055)^2.4``."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)
