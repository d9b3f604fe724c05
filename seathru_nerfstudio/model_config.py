"""The options of :class:`~seathru_nerfstudio.model.SeathruModel`: a short list a user sets, and the
research switches (oracles, ablation estimators, the schedule's inner constants) under one
nested :class:`ResearchConfig` (``--pipeline.model.research.*``).

Why each default is what it is, with the runs that measured it: docs/history.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Type

from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.configs.base_config import PrintableConfig
from nerfstudio.models.nerfacto import NerfactoModelConfig

from seathru_nerfstudio.input_errors import InputError
from seathru_nerfstudio.medium_choice import ChoiceRule
from seathru_nerfstudio.medium_field import MEDIUM_MODELS
from seathru_nerfstudio.rendering import Quadrature


@dataclass
class ResearchConfig(PrintableConfig):
    """Diagnostics and research switches: oracles, ablation estimators and inner constants of the
    training schedule. None of them is needed to train a scene."""

    medium_oracle: Optional[Path] = None
    """A ``medium.json`` (``beta_D``, ``beta_B`` in 1/world unit, ``B_inf``) held fixed as the medium."""
    medium_oracle_learns: bool = False
    """With ``medium_oracle``: start the scene medium at the oracle and let it learn."""
    medium_fit_oracle: Optional[Path] = None
    """A ``medium.json`` whose densities replace the medium fit's at ``medium_fit_step``."""
    medium_fit_oracle_parts: Literal["both", "attenuation", "backscatter"] = "both"
    """Which densities ``medium_fit_oracle`` replaces: both, ``β_D`` alone or ``β_B`` alone."""
    depth_source: Literal["sfm", "ground-truth"] = "sfm"
    """Depth loss target: the sparse SfM depths, or a synthetic scene's dense true range."""
    auto_decision_step: int = 500
    """``medium_model auto``: the step at which the medium model is chosen."""
    auto_evidence_steps: int = 50
    """``auto``: the evidence is the mean over this many steps before the decision."""
    auto_blend_steps: int = 200
    """Steps over which the medium moves to ``auto``'s choice (the object density held) and the held densities to the medium fit."""
    auto_rule: ChoiceRule = field(default_factory=ChoiceRule)
    """``auto``: thresholds of the decision (:mod:`seathru_nerfstudio.medium_choice`)."""
    medium_fit_max_log_error: float = 0.35
    """A channel keeps its trained densities where the fit's standard error of ``ln β_D`` is above this."""
    surface_veil_optical_depth: Optional[float] = 3.0
    """The veil in front of the surfaces is read from those at least this optical depth away (``None``: one veil)."""
    medium_init_density: float = 0.5
    """Starting densities per scene unit where ``medium_init_optical_depth`` cannot apply (no SfM depths)."""
    backscatter_excess_mult: float = 10.0
    """Weight of the loss on backscatter above the image (keeps dim channels alive early); 0: off."""
    backscatter_excess_steps: int = 500
    """Steps during which the backscatter excess loss applies."""
    binary_prior_early_mult: Optional[float] = 1e-3
    """The binary prior's weight up to ``medium_fit_step`` (``None``: ``binary_prior_mult`` throughout)."""
    binary_prior_scale: float = 0.1
    """Scale of the two Laplacians of the binary prior."""
    depth_sigma: float = 0.02
    """Floor of the depth loss's kernel width, metres; it widens to the sample interval at the depth."""
    rawnerf_eps: float = 1e-3
    """Epsilon of RawNeRF's relative loss."""


@dataclass
class SeathruModelConfig(NerfactoModelConfig):
    """SeaThru-NeRF: nerfacto's object field and sampling, a scattering medium, the paper's losses."""

    _target: Type = field(default_factory=lambda: _model_class())
    medium_model: Literal["auto", "none", "fog", "uniform", "seathru", "basic"] = "auto"
    """How much medium: auto (choose at ``research.auto_decision_step``), none, fog, uniform, seathru (sec. 4.3), basic (sec. 4.1)."""
    medium_scope: Literal["ray", "scene"] = "scene"
    """``scene``: one homogeneous water body (nine constants); ``ray``: the paper's MLP of the view direction."""
    medium_num_layers: int = 2
    """Hidden layers of the medium MLP (``medium_scope ray``; the paper uses 6)."""
    medium_hidden_dim: int = 64
    """Width of the medium MLP (``medium_scope ray``; the paper uses 256)."""
    medium_sh_levels: int = 4
    """Spherical-harmonic levels of the medium MLP's direction encoding."""
    medium_init_optical_depth: float = 3.0
    """Start the densities so that the mean SfM range is this many attenuation lengths away (0: ``research.medium_init_density``); both are capped by the SfM observations when the object field enters (``medium_start``)."""
    object_view_dependent: Optional[bool] = None
    """View-dependent object colour (nerfacto); False: Lambertian, as the official code; None: Lambertian in a medium, view-dependent in clear air."""
    depth_loss_mult: float = 0.1
    """Weight of the DS-NeRF loss on the dataset's sparse SfM depths (0: off); through a medium the images pin the range weakly."""
    clear_air_depth_loss_mult: float = 3e-3
    """That weight under the ``none`` model, where the images alone pin the range (0: off)."""
    diagnostics_every: int = 100
    """Print one line of decomposition diagnostics every this many steps; 0: never."""
    far_bound_margin: float = 2.0
    """The object field ends at this multiple of the SfM far bound (0: nerfacto's ``far_plane``)."""
    render_from_near_bound: bool = True
    """Renders start rays at the SfM near bound, as training does (off: at 0, as nerfacto)."""
    medium_first_steps: int = 200
    """Steps in which the image shows an empty scene: the veiling light and the SfM geometry learn first."""
    medium_fit_step: Optional[int] = 500
    """Fit the densities to the SfM points' colours across views after this step, then hold them; ``None``: off."""
    quadrature: Quadrature = "analytic"
    """``analytic``: exact per-interval integral; ``paper``: the sec. 4.3 sums as printed."""
    color_space: Literal["linear", "srgb"] = "linear"
    """``linear`` (RAW) data trains with RawNeRF's relative L2, ``srgb`` with plain L2."""
    binary_prior_mult: float = 1e-4
    """Weight of the binary prior on the object transmittance after the medium fit (the paper's λ)."""
    binary_prior_empty_weight: float = 6.0
    """How much more the binary prior likes empty space (T = 1) than solid (T = 0)."""
    research: ResearchConfig = field(default_factory=ResearchConfig)
    """Diagnostics and research switches."""
    # Departures from nerfacto's defaults, as the paper: no distortion loss, no per-image
    # appearance code (it could explain the water away), no pose refinement.
    distortion_loss_mult: float = 0.0
    use_appearance_embedding: bool = False
    background_color: Literal["random", "last_sample", "black", "white"] = "last_sample"
    """Behind the object field in clear air (``none``); with a medium the water is behind everything."""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Refuse settings this model cannot train with, naming the option, as an :class:`InputError` (also called when the
        model is built, for configs changed after construction)."""
        research = self.research
        if research.medium_oracle is not None and self.medium_model == "auto":
            self.medium_model = "seathru"  # an oracle is the medium: nothing to choose, and a tie would change it
        if self.medium_model != "auto" and self.medium_model not in MEDIUM_MODELS:
            raise InputError(
                f"--pipeline.model.medium-model: unknown {self.medium_model!r}; expected auto or one of {', '.join(MEDIUM_MODELS)}"
            )
        for name, value in (("medium-first-steps", self.medium_first_steps), ("medium-fit-step", self.medium_fit_step)):
            if value is not None and value < 0:
                raise InputError(f"--pipeline.model.{name} must be >= 0 (got {value})")
        if self.medium_fit_step is not None and self.medium_fit_step <= self.medium_first_steps:
            raise InputError(
                f"--pipeline.model.medium-fit-step ({self.medium_fit_step}) must come after --pipeline.model.medium-first-steps "
                f"({self.medium_first_steps}): the fit reads the veiling light learned in that stage (None turns the fit off)"
            )
        if self.medium_model == "auto" and not (
            self.medium_first_steps < research.auto_decision_step and 0 < research.auto_evidence_steps
        ):
            raise InputError(
                f"--pipeline.model.research.auto-decision-step ({research.auto_decision_step}) must come after "
                f"--pipeline.model.medium-first-steps ({self.medium_first_steps}), with auto-evidence-steps "
                f"({research.auto_evidence_steps}) > 0"
            )
        if research.medium_fit_oracle is not None and (self.medium_fit_step is None or research.medium_oracle is not None):
            raise InputError(
                "--pipeline.model.research.medium-fit-oracle replaces the fit of --pipeline.model.medium-fit-step: "
                "set that step, without research.medium-oracle"
            )
        for path_name, path in (("medium-oracle", research.medium_oracle), ("medium-fit-oracle", research.medium_fit_oracle)):
            if path is not None and not Path(path).is_file():
                raise InputError(f"--pipeline.model.research.{path_name}: {path} does not exist")
        if research.surface_veil_optical_depth is not None and not research.surface_veil_optical_depth > 0:
            raise InputError(
                f"--pipeline.model.research.surface-veil-optical-depth must be > 0 or None (got {research.surface_veil_optical_depth})"
            )
        if not research.medium_fit_max_log_error > 0:  # NaN fails too
            raise InputError(f"--pipeline.model.research.medium-fit-max-log-error must be > 0 (got {research.medium_fit_max_log_error})")
        early = research.binary_prior_early_mult
        if not (early is None or early >= 0) or research.backscatter_excess_steps < 0:  # NaN fails too
            raise InputError(
                "--pipeline.model.research.binary-prior-early-mult must be None or >= 0 and backscatter-excess-steps >= 0 "
                f"(got {early} and {research.backscatter_excess_steps})"
            )
        for name, value in (("binary-prior-mult", self.binary_prior_mult), ("depth-loss-mult", self.depth_loss_mult),
                            ("clear-air-depth-loss-mult", self.clear_air_depth_loss_mult)):
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"--pipeline.model.{name} must be finite and >= 0 (got {value})")
        if self.predict_normals:
            raise InputError(
                "--pipeline.model.predict-normals True is not supported: the model renders no normals "
                "(for ns-export use --normal-method open3d)"
            )


def _model_class() -> Type:
    from seathru_nerfstudio.model import SeathruModel

    return SeathruModel
