"""The medium: veiling-light colour, attenuation and backscatter densities of the water.

The medium is constant along a ray (paper sec. 3.1), so it is evaluated once per ray, never
per sample. Three variants share one interface, ``medium(directions) -> MediumOutputs``:

* :class:`MediumField`, the paper's MLP of the ray direction (``per-ray``): water whose
  colour and turbidity vary with the viewing direction, e.g. towards the surface;
* :class:`SceneMedium`, nine learned constants (``per-scene``): one homogeneous water
  body, which is what the SeaThru image formation model assumes;
* :class:`FixedMedium`, given constants (an oracle for experiments: the true medium).

Each of them has six densities; :func:`tie` makes the simpler medium models of
:data:`MEDIUM_MODELS` from them by averaging (``fog``: one attenuation for all channels,
``uniform``: one per channel for attenuation and backscatter), so that every model has the
same parameters and a switch between models keeps the medium learned so far.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Dict, Literal, Sequence, Tuple

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


MediumModel = Literal["none", "fog", "uniform", "seathru", "basic"]
"""How much medium a scene gets (``SeathruModelConfig.medium_model``):

* ``none``: clear air; nothing is evaluated, ``rgb = clean`` (nerfacto's rendering);
* ``fog``: one attenuation for all channels (droplets much larger than the wavelength extinguish
  every colour alike, the paper's sec. 3), and a backscatter density per channel: in the SeaThru model
  that density also carries how the light that scatters is spread over directions and colours, which is
  not grey under a blue sky. On path-traced fog (layouts 3 and 4, the SfM observations under the veil the
  runs held) tying the backscatter too raised the fit's residual 0.6–0.8% over six free densities and
  took the grey attenuation from 2% to 12% and from 19% to 29% under the truth; tying the attenuation
  alone moved the residual by under 0.1%
  (docs/history.md, 2026-12-03 (fog's backscatter per channel)). The paper's fog also ties attenuation
  to backscatter; physically rendered fog does not (its best-fitting backscatter density is 0.7–0.8 of
  its attenuation);
* ``uniform``: one density per channel, shared by attenuation and backscatter;
* ``seathru``: separate attenuation and backscatter densities per channel (sec. 4.3, "final");
* ``basic``: the paper's basic model (sec. 4.1, eqs. 11-13: one medium density per channel),
  kept under its own name for the ablation; it ties the densities as ``uniform`` does.
"""

MEDIUM_MODELS: Tuple[str, ...] = ("none", "fog", "uniform", "seathru", "basic")
"""Every medium model, the simplest first; a model's index here is what checkpoints record."""

def tie_matrix(model: str) -> Float[Tensor, "6 K"]:
    """0/1 matrix from the ``K`` densities ``model`` keeps free to ``(β_D RGB, β_B RGB)``: the one
    table of which densities a medium model keeps equal, for rendering (:func:`tie`) and for the
    fit (:mod:`seathru_nerfstudio.medium_fit`). ``seathru`` six free, ``uniform`` and ``basic`` one
    per channel, ``fog`` one attenuation for all channels and a backscatter density per channel."""
    if model == "seathru":
        return torch.eye(6, dtype=torch.float64)
    if model in ("uniform", "basic"):
        return torch.cat([torch.eye(3, dtype=torch.float64)] * 2)
    if model == "fog":  # one grey attenuation; the backscatter density per channel
        matrix = torch.zeros(6, 4, dtype=torch.float64)
        matrix[:3, 0] = 1.0
        matrix[3:, 1:] = torch.eye(3, dtype=torch.float64)
        return matrix
    raise ValueError(f"tie_matrix: no medium densities for model {model!r}; expected one of {MEDIUM_MODELS[1:]}")


FREE_DENSITIES: Dict[str, int] = {"none": 0, **{model: tie_matrix(model).shape[1] for model in MEDIUM_MODELS[1:]}}
"""How many medium densities each model learns (per ray or per scene)."""


def tie(medium: "MediumOutputs", model: str) -> "MediumOutputs":
    """``medium`` with its densities tied as ``model`` asks (:func:`tie_matrix`), each to the
    mean of its group: ``fog`` gives every channel the mean attenuation,
    ``uniform`` and ``basic`` give attenuation and backscatter their per-channel mean, ``seathru``
    keeps them. (``none`` has no medium: the model never calls this for it.) With tied inputs
    the result is the input. Selections, sums and a gather (no product with the 0/1 matrix, so no
    0·inf), all elementwise: autocast keeps the input dtype."""
    if FREE_DENSITIES.get(model) == 6:
        return medium
    sigma = torch.cat([medium.sigma_attn, medium.sigma_bs], dim=-1)
    member, group_size, group_of = _tie_groups(model, sigma.device)
    group_mean = torch.where(member, sigma[..., :, None], 0).sum(dim=-2) / group_size
    tied = group_mean[..., group_of]  # each density takes its group's mean
    return MediumOutputs(rgb=medium.rgb, sigma_attn=tied[..., :3], sigma_bs=tied[..., 3:])


@functools.lru_cache(maxsize=None)
def _tie_groups(model: str, device: torch.device) -> Tuple[Tensor, Tensor, Tensor]:
    """:func:`tie_matrix` as ``tie`` reads it, made once per model and device (``tie`` runs on
    every ray batch): membership ``(6, K)`` bool, group sizes ``(K,)`` int64, each density's group ``(6,)``."""
    matrix = tie_matrix(model)
    member = matrix.to(device=device, dtype=torch.bool)
    return member, member.sum(dim=0), matrix.argmax(dim=1).to(device)  # integer sizes: the mean keeps its dtype


def clear_medium(directions: Float[Tensor, "*batch 3"]) -> "MediumOutputs":
    """The ``none`` model's medium, exactly: no veiling light and zero densities (the
    outputs contract holds these values without evaluating any medium)."""
    zeros = torch.zeros_like(directions, dtype=torch.float32)
    return MediumOutputs(rgb=zeros, sigma_attn=zeros, sigma_bs=zeros)


def blend_media(start: "MediumOutputs", end: "MediumOutputs", weight: float) -> "MediumOutputs":
    """``(1 - weight) start + weight end``, colour and densities alike (``weight`` in [0, 1])."""
    def mix(a: Tensor, b: Tensor) -> Tensor:
        return torch.lerp(a, b.to(a.dtype), weight)

    return MediumOutputs(
        rgb=mix(start.rgb, end.rgb), sigma_attn=mix(start.sigma_attn, end.sigma_attn), sigma_bs=mix(start.sigma_bs, end.sigma_bs)
    )


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
        self.register_buffer("density_bias", torch.full((6,), inverse_softplus(init_density)), persistent=False)
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


def inverse_softplus(value: float) -> float:
    """``x`` with ``softplus(x) = value`` (``value > 0``)."""
    return float(torch.log(torch.expm1(torch.tensor(float(value), dtype=torch.float64))))


def _expand(values: Tensor, directions: Tensor) -> Tensor:
    return values.to(directions.device).expand(*directions.shape[:-1], 3)


def sin_elevation(directions: Float[Tensor, "*batch 3"], vertical: Float[Tensor, "3"]) -> Float[Tensor, "*batch 1"]:
    """``sin`` of the elevation of unit ``directions`` above the level plane: ``direction · vertical``
    (``vertical``: the scene's unit up), clamped to [-1, 1]."""
    return (directions.float() @ vertical.to(directions.device).float()).unsqueeze(-1).clamp(-1.0, 1.0)


def level_axes(vertical: Float[Tensor, "3"]) -> Float[Tensor, "3 2"]:
    """:func:`~seathru_nerfstudio.vertical.level_frame` of ``vertical`` (normalised here; ``+z`` for a
    zero vector). Computed once per vertical (it reads the vertical on the CPU), not per batch. float32,
    on ``vertical``'s device."""
    from seathru_nerfstudio.vertical import level_frame

    up = vertical.detach().double().cpu()
    up = up / up.norm() if float(up.norm()) > 0 else torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    return level_frame(up).float().to(vertical.device)


def level_components(directions: Float[Tensor, "*batch 3"], axes: Float[Tensor, "3 2"]) -> Float[Tensor, "*batch 2"]:
    """The components of unit ``directions`` along the level ``axes`` (:func:`level_axes`), each in
    [-1, 1] (``up² + h1² + h2² = 1``): where a ray looks round the horizon."""
    return (directions.float() @ axes.to(directions.device).float()).clamp(-1.0, 1.0)


SURFACE_VEIL_BUFFERS = ("surface_veil", "surface_veil_from", "surface_veil_to")
"""Buffers a checkpoint from before the surfaces' veil lacks (they keep 1: one veil)."""


class SceneMedium(nn.Module):
    """One homogeneous water body: ``c_med``, ``sigma_attn`` and ``sigma_bs`` are nine
    learned constants (sigmoid and softplus, as the MLP's heads). The densities are the same for
    every ray; the veil is ``c_med`` for every ray except those looking up past a held elevation,
    where it rises linearly (:meth:`set_veil_rise`; no rise until it is set): light falls from
    above, so open water brightens looking up while the water itself stays one body. Round the
    horizon it changes linearly with the ray's level components (:meth:`set_veil_across`): a sun
    to one side lights the water that way more, through the phase function, at every range alike.

    Cheaper than :class:`MediumField` and without its freedom to give every ray its own
    water, which on a homogeneous scene lets the medium explain scene content per ray.
    """

    def __init__(
        self, init_density: float | Sequence[float] = 0.5, init_rgb: float | Sequence[float] = 0.5
    ) -> None:
        """``init_density``: one value for all six densities, or ``sigma_attn`` then ``sigma_bs``
        per channel (per scene unit, > 0); ``init_rgb``: one value or three, in (0, 1)."""
        super().__init__()
        rgb = torch.as_tensor(init_rgb, dtype=torch.float64).expand(3)
        self.rgb_logit = nn.Parameter(torch.logit(rgb).float().clone())
        densities = torch.as_tensor(init_density, dtype=torch.float64).expand(6)
        self.density_raw = nn.Parameter(torch.zeros(6))
        self.set_densities(densities)
        self.register_buffer("vertical", torch.tensor([0.0, 0.0, 1.0]), persistent=False)
        """The unit up of the scene frame for the elevation (:func:`~seathru_nerfstudio.vertical.scene_vertical`;
        set from the data at every start, so not in checkpoints)."""
        self.register_buffer("level_axes", level_axes(self.vertical), persistent=False)
        """:func:`level_axes` of :attr:`vertical`, set with it."""
        self.register_buffer("veil_rise_from", torch.ones(3))
        """Where the veil starts to rise, per channel: ``sin`` of the elevation (``direction · vertical``)."""
        self.register_buffer("veil_rise", torch.zeros(3))
        """The veil's rise over ``c_med`` per unit of ``sin(elevation)`` above :attr:`veil_rise_from` (per channel, >= 0)."""
        self.register_buffer("veil_rise_to", torch.tensor(1.0))
        """Where the rise ends (``sin`` of the elevation): above it the veil stays at its value there."""
        self.register_buffer("veil_across", torch.zeros(2, 3))
        """The veil's relative change per unit of each level component (:func:`level_components`), per channel."""
        self.register_buffer("veil_across_mean", torch.zeros(2))
        """The level components at which the change is 0 (the open rays' mean)."""
        self.register_buffer("veil_across_low", torch.zeros(2))
        """Below this, per level component, the change stays at its value there (the open water seen)."""
        self.register_buffer("veil_across_high", torch.zeros(2))
        """Above this, per level component, the change stays at its value there."""
        self.register_buffer("fit_from", torch.zeros(6))
        """The densities before the medium fit and (:attr:`fit_to`) the fit, per scene unit, between which
        :meth:`move_to_fit` moves them (zeros: no fit yet); in checkpoints, so a resumed run moves alike."""
        self.register_buffer("fit_to", torch.zeros(6))
        self.register_buffer("surface_veil", torch.ones(3))
        """The veil in front of the surfaces over ``c_med``, per channel in (0, 1] (:mod:`~seathru_nerfstudio.surface_veil`);
        moves from :attr:`surface_veil_from` to :attr:`surface_veil_to` with the densities (:meth:`move_to_fit`)."""
        self.register_buffer("surface_veil_from", torch.ones(3))
        self.register_buffer("surface_veil_to", torch.ones(3))

    def set_veil_rise(self, start: float | Float[Tensor, "3"], rise: Float[Tensor, "3"], end: float = 1.0) -> None:
        """Hold the veil at ``c_med (1 + rise clamp(up - start, 0, end - start))``, ``up = sin(elevation)``;
        ``start``: one elevation or one per channel."""
        with torch.no_grad():
            self.veil_rise_from.copy_(torch.as_tensor(start, dtype=self.veil_rise_from.dtype).expand(3))
            self.veil_rise.copy_(rise.clamp_min(0.0))
            self.veil_rise_to.fill_(max(float(end), float(self.veil_rise_from.max())))

    def set_veil_across(
        self, mean: Float[Tensor, "2"], change: Float[Tensor, "2 3"], low: Float[Tensor, "2"], high: Float[Tensor, "2"]
    ) -> None:
        """Hold the veil's factor round the horizon at ``max(0, 1 + Σ_j change_j (clamp(h_j, low_j, high_j) − mean_j))``,
        ``h`` the ray's :func:`level_components`; ``change``: relative, per unit of ``h``, per channel."""
        with torch.no_grad():
            self.veil_across.copy_(torch.as_tensor(change, dtype=torch.float32).reshape(2, 3))
            self.veil_across_mean.copy_(torch.as_tensor(mean, dtype=torch.float32).reshape(2))
            self.veil_across_low.copy_(torch.as_tensor(low, dtype=torch.float32).reshape(2))
            self.veil_across_high.copy_(torch.maximum(torch.as_tensor(high, dtype=torch.float32).reshape(2), self.veil_across_low))

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):  # noqa: ANN001
        """A checkpoint from before the start was per channel holds one start: every channel takes it.
        One from before the change round the horizon or the surfaces' veil has none: those buffers keep what
        they hold (a factor of 1 on a new model) and are not reported missing. Nothing is added to ``state_dict``:
        nerfstudio loads the pipeline's own keys into every module after the model's."""
        key = prefix + "veil_rise_from"
        if key in state_dict and state_dict[key].dim() == 0:
            state_dict[key] = state_dict[key].expand(3).clone()
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs)
        for name in ("veil_across", "veil_across_mean", "veil_across_low", "veil_across_high") + SURFACE_VEIL_BUFFERS:
            if prefix + name in missing_keys:
                missing_keys.remove(prefix + name)

    def set_vertical(self, vertical: Sequence[float] | Tensor) -> None:
        """The scene frame's up (three numbers, normalised here) along which the elevation is measured;
        a ``ValueError`` for a zero or non-finite vector, which has no direction."""
        values = torch.as_tensor(vertical, dtype=torch.float64).reshape(3)
        if not (bool(torch.isfinite(values).all()) and float(values.norm()) > 0):
            raise ValueError(f"the scene's vertical must be a finite non-zero vector, got {values.tolist()}")
        with torch.no_grad():
            self.vertical.copy_(values / values.norm())
            self.level_axes.copy_(level_axes(self.vertical))

    def veil_gain(self, directions: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3"]:
        """``1 + rise clamp(up - start, 0, end - start)`` for rays with these unit directions, ``up`` their
        :func:`sin_elevation` along :attr:`vertical` (1 below ``start``)."""
        up = sin_elevation(directions, self.vertical)
        above = torch.minimum(up, self.veil_rise_to) - self.veil_rise_from
        return 1.0 + self.veil_rise * above.clamp_min(0.0)

    def across_gain(self, directions: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3"]:
        """The veil's factor round the horizon (:meth:`set_veil_across`) for rays with these unit
        directions: 1 at the held mean, linear in the level components within the range held, >= 0."""
        h = level_components(directions, self.level_axes)
        h = torch.minimum(torch.maximum(h, self.veil_across_low), self.veil_across_high) - self.veil_across_mean
        return (1.0 + h @ self.veil_across).clamp_min(0.0)

    def rendered_veil_gain(self, directions: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3"]:
        """:meth:`veil_gain` as :meth:`forward` renders it (capped where ``c_med`` times it and
        :meth:`across_gain` reaches 1), no gradient: what
        :func:`~seathru_nerfstudio.rendering.render_seathru` takes as ``veil_gain``. The factor round
        the horizon is not in it: it scales the whole path radiance, near and far alike."""
        with torch.no_grad():
            level = torch.sigmoid(self.rgb_logit.float()).to(directions.device) * self.across_gain(directions)
            return torch.minimum(self.veil_gain(directions), 1.0 / level.clamp_min(torch.finfo(torch.float32).tiny))

    def set_densities(self, densities: Sequence[float] | Tensor, first: int = 0) -> None:
        """Set the densities ``first, first + 1, ...`` (``sigma_attn`` then ``sigma_bs``, per scene
        unit, > 0) to ``densities`` exactly, through the inverse of the softplus."""
        values = [inverse_softplus(float(d)) for d in densities]
        with torch.no_grad():
            self.density_raw[first : first + len(values)].copy_(torch.tensor(values, dtype=self.density_raw.dtype))

    def start_move_to_fit(self, fitted: Float[Tensor, "6"], surface_veil: Float[Tensor, "3"] | None = None) -> None:
        """Record the densities now and ``fitted`` (per scene unit, > 0) as the ends of :meth:`move_to_fit`, and
        likewise the surfaces' veil now and ``surface_veil`` (in (0, 1]; ``None``: it stays)."""
        with torch.no_grad():
            self.fit_from.copy_(nn.functional.softplus(self.density_raw.double()).float())
            self.fit_to.copy_(fitted.float())
            self.surface_veil_from.copy_(self.surface_veil)
            target = self.surface_veil if surface_veil is None else torch.as_tensor(surface_veil).to(self.surface_veil)
            self.surface_veil_to.copy_(target.clamp(torch.finfo(torch.float32).tiny, 1.0))

    def move_to_fit(self, share: float, held: Tensor) -> None:
        """Set the ``held`` densities (six booleans) to ``from^(1 - share) · to^share`` (log space; ``share``
        in [0, 1]); the others keep what they learned; nothing before a fit."""
        if not bool((self.fit_from > 0).all() and (self.fit_to > 0).all()):
            return
        share = min(max(float(share), 0.0), 1.0)
        moved = torch.exp(torch.lerp(self.fit_from.double().log(), self.fit_to.double().log(), share))
        now = nn.functional.softplus(self.density_raw.detach().double())
        self.set_densities(torch.where(held.to(moved.device).bool(), moved, now))
        with torch.no_grad():
            log_from, log_to = self.surface_veil_from.double().log(), self.surface_veil_to.double().log()
            self.surface_veil.copy_(torch.exp(torch.lerp(log_from, log_to, share)).float())

    def density_parameters(self) -> list:
        """The attenuation and backscatter densities: weakly determined by the images, so they
        learn in their own, slower optimiser group; the veiling light is seen directly in open water."""
        return [self.density_raw]

    def forward(self, directions: Float[Tensor, "*batch 3"]) -> MediumOutputs:
        densities = nn.functional.softplus(self.density_raw.float())
        return MediumOutputs(
            rgb=(
                torch.sigmoid(self.rgb_logit.float()).to(directions.device) * self.veil_gain(directions) * self.across_gain(directions)
            ).clamp(max=1.0),
            sigma_attn=_expand(densities[:3], directions),
            sigma_bs=_expand(densities[3:], directions),
        )


class FixedMedium(nn.Module):
    """A given homogeneous medium (no parameters): the oracle of an experiment.

    ``sigma_attn`` and ``sigma_bs`` per scene unit, ``rgb`` linear; three values each.
    """

    def __init__(self, rgb: Sequence[float], sigma_attn: Sequence[float], sigma_bs: Sequence[float]) -> None:
        super().__init__()
        for name, values in (("rgb", rgb), ("sigma_attn", sigma_attn), ("sigma_bs", sigma_bs)):
            if len(values) != 3:
                raise ValueError(f"FixedMedium: {name} needs 3 values, got {list(values)}")
        self.register_buffer("rgb", torch.tensor([float(v) for v in rgb]), persistent=False)
        self.register_buffer("sigma_attn", torch.tensor([float(v) for v in sigma_attn]), persistent=False)
        self.register_buffer("sigma_bs", torch.tensor([float(v) for v in sigma_bs]), persistent=False)

    def forward(self, directions: Float[Tensor, "*batch 3"]) -> MediumOutputs:
        return MediumOutputs(
            rgb=_expand(self.rgb, directions),
            sigma_attn=_expand(self.sigma_attn, directions),
            sigma_bs=_expand(self.sigma_bs, directions),
        )
