"""The medium MLP: ray direction -> veiling-light colour, attenuation and backscatter densities.

The medium is constant along a ray (paper sec. 3.1), so this field is evaluated once per
ray, never per sample.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor, nn

from nerfstudio.field_components.encodings import SHEncoding
from nerfstudio.field_components.mlp import MLP
from nerfstudio.fields.base_field import get_normalized_directions


@dataclass
class MediumOutputs:
    """Per-ray medium parameters. Densities are per scene unit (world units times the
    dataparser scale); colours are linear."""

    rgb: Float[Tensor, "*batch 3"]
    """``c_med``: the veiling light, backscatter colour at infinity (``B_inf``)."""
    sigma_attn: Float[Tensor, "*batch 3"]
    """``sigma_attn``: attenuation of the direct signal (``beta_D``)."""
    sigma_bs: Float[Tensor, "*batch 3"]
    """``sigma_bs``: backscatter density (``beta_B``)."""


class MediumField(nn.Module):
    """Spherical-harmonic direction encoding followed by an MLP with three heads.

    ``c_med`` goes through a sigmoid, ``sigma_attn`` and ``sigma_bs`` through a softplus,
    three channels each (paper sec. 3.5).
    """

    def __init__(
        self,
        num_layers: int = 2,
        hidden_dim: int = 64,
        sh_levels: int = 4,
        init_density: float = 0.5,
        implementation: Literal["tcnn", "torch"] = "torch",
    ) -> None:
        super().__init__()
        self.direction_encoding = SHEncoding(levels=sh_levels, implementation=implementation)
        self.mlp = MLP(
            in_dim=self.direction_encoding.get_out_dim(),
            num_layers=num_layers,
            layer_width=hidden_dim,
            out_dim=9,
            activation=nn.Softplus(),
            out_activation=None,
            implementation=implementation,
        )
        # Start from a moderate medium rather than softplus(0) ~ 0.69 per scene unit.
        inverse_softplus = float(torch.log(torch.expm1(torch.tensor(init_density))))
        self.register_buffer("density_bias", torch.full((6,), inverse_softplus), persistent=False)
        self.activation = nn.Softplus()

    def forward(self, directions: Float[Tensor, "*batch 3"]) -> MediumOutputs:
        """``directions`` are unit ray directions in world coordinates."""
        encoded = self.direction_encoding(get_normalized_directions(directions).reshape(-1, 3))
        raw = self.mlp(encoded).reshape(*directions.shape[:-1], 9).float()
        densities = self.activation(raw[..., 3:] + self.density_bias)
        return MediumOutputs(
            rgb=torch.sigmoid(raw[..., :3]),
            sigma_attn=densities[..., :3],
            sigma_bs=densities[..., 3:],
        )
