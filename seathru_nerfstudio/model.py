"""SeaThru-NeRF as a nerfacto subclass: nerfacto's object field and proposal sampling,
plus a per-ray medium field and the scattering renderer of :mod:`seathru_nerfstudio.rendering`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple, Type

import torch
from torch.nn import Parameter

from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.model_components.losses import DepthLossType, depth_loss, scale_gradients_by_distance_squared
from nerfstudio.model_components.scene_colliders import NearFarCollider
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio import diagnostics, metrics, viewer
from seathru_nerfstudio.medium_choice import ChoiceRule, MediumEvidence, choose_medium_model
from seathru_nerfstudio.lazy_outputs import LazyOutputs
from seathru_nerfstudio.losses import (
    backscatter_envelope_loss,
    backscatter_excess_loss,
    binary_transmittance_loss,
    depth_kernel_variance,
    rawnerf_loss,
)
from seathru_nerfstudio.contraction import ContractionBeyond
from seathru_nerfstudio.data.nerfstudio_data import EXTENT_KEY, RANGE_SPREAD_KEY, SCALE_KEY, SFM_OBSERVATIONS_KEY
from seathru_nerfstudio.medium_field import (
    MEDIUM_MODELS,
    FixedMedium,
    MediumField,
    MediumOutputs,
    SceneMedium,
    blend_media,
    clear_medium,
    inverse_softplus,
    tie,
)
from seathru_nerfstudio.medium_fit import fit_densities
from seathru_nerfstudio.rendering import Quadrature, SeathruRender, object_weights, render_seathru

WATER_OUTPUTS = ("rgb", "direct", "backscatter")
"""Outputs that need the object field and the medium."""
OBJECT_OUTPUTS = ("clean", "depth", "expected_depth", "accumulation")
"""Outputs of the object field alone (with the proposal depths ``prop_depth_<i>``)."""
MEDIUM_OUTPUTS = ("medium_rgb", "medium_attenuation", "medium_backscatter")
"""Per-ray medium maps: the medium alone, without the object field."""

UNDECIDED = -1
"""``medium_model_code`` of an ``auto`` run before its decision (it renders ``seathru``)."""

@dataclass
class SeathruModelConfig(NerfactoModelConfig):
    """SeaThru-NeRF: nerfacto's settings, plus the medium and the paper's losses."""

    _target: Type = field(default_factory=lambda: SeathruModel)
    medium_num_layers: int = 2
    """Hidden layers of the medium MLP (the paper uses 6)."""
    medium_hidden_dim: int = 64
    """Width of the medium MLP (the paper uses 256)."""
    medium_sh_levels: int = 4
    """Spherical-harmonic levels of the medium's direction encoding."""
    medium_init_density: float = 0.5
    """Initial sigma_attn and sigma_bs, per scene unit, where ``medium_init_optical_depth`` does
    not apply (a dataset without SfM depths, or 0 there)."""
    medium_init_optical_depth: float = 3.0
    """Initial sigma_attn and sigma_bs such that the SfM points' mean range (the dataparser's
    ``sfm_range_spread``) is this many attenuation lengths away, whatever the rig's width. A
    scene unit follows the rig (nerfstudio scales the poses), not the distance to the scene, so
    ``medium_init_density`` started turbid water (objects 3.4x farther than water's, rig 1.5x
    wider) at an optical depth of 6.5, where the objects' light and with it the attenuation's
    gradient (``-z J e^{-beta z}``) vanish: green beta_D stayed 2.7x the truth. 3.0 is the
    optical depth ``medium_init_density`` gave the water and fog demos (1.88 /m at 1.58 m).
    On a flat rig the images barely tell the attenuation, and training stops it short of the
    truth on the side it started from (docs/benchmarks.md, session 15: fog from 1.89 /m to 1.40
    and from 0.95 to 1.04, truth 1.2; 1.5 won on water and lost on fog and turbid water), so if
    you know the water's attenuation length, start there. 0: off."""
    medium_scope: Literal["ray", "scene"] = "scene"
    """``ray``: the paper's MLP of the ray direction (water that changes with the viewing
    direction). ``scene``: one homogeneous water body, nine learned constants."""
    medium_oracle: Optional[Path] = None
    """Diagnostic: a ``medium.json`` (``beta_D``, ``beta_B`` in 1/world unit, ``B_inf``, as
    ``seathru-synth`` writes) whose medium is held fixed; only the object field learns. Keep
    ``first_stage_geometry`` on (the default): without it, the object field trained under the true medium from
    step 0 loses its green and blue colour within 20 steps and settles at twice the range
    (docs/benchmarks.md, session 4)."""
    medium_oracle_learns: bool = False
    """Diagnostic, with ``medium_oracle``: the per-scene medium starts at the oracle's values and
    learns, instead of being held: does the objective keep the true medium, or move away from it?"""
    object_view_dependent: bool = False
    """Object colour depends on the view direction (nerfacto). Off: Lambertian colour, as
    the official SeaThru-NeRF; then a view-dependent look must come from the medium."""
    depth_loss_mult: float = 1e-2
    """Weight of nerfacto's DS-NeRF depth loss (mean over the rays that have a depth); 0: off.
    Its source is ``depth_source``; a dataset without depth images trains without it."""
    depth_source: Literal["sfm", "ground-truth"] = "sfm"
    """``sfm``: the dataset's depth images (nerfstudio's ``depth_file_path``; sparse SfM
    depths, 0 where unknown). ``ground-truth``: diagnostic, the synthetic scenes' true range
    (dense), and zero object opacity where the truth is open water."""
    depth_sigma: float = 0.02
    """Spread of the depth loss, in world units (metres); with ``depth_sigma_follows_sampling``
    its floor."""
    depth_sigma_follows_sampling: bool = True
    """Widen the depth loss's kernel on each ray to the length of the sample interval at the
    known depth where that is longer than ``depth_sigma``
    (:func:`~seathru_nerfstudio.losses.depth_kernel_variance`): a kernel narrower than the
    sampling falls between samples and trains nothing. Off: ``depth_sigma`` everywhere."""
    diagnostics_every: int = 100
    """Print one line of decomposition diagnostics every this many steps; 0: never."""
    medium_model: Literal["auto", "none", "fog", "uniform", "seathru", "basic"] = "auto"
    """How much medium the scene gets (:data:`~seathru_nerfstudio.medium_field.MediumModel`):
    ``none`` (clear air: nerfacto's rendering, no medium evaluated), ``fog`` (one density),
    ``uniform`` (one density per channel), ``seathru`` (attenuation and backscatter per channel,
    sec. 4.3; ``final`` in older configs), ``basic`` (sec. 4.1, for the ablation). ``auto``:
    ``seathru`` until ``medium_auto_decision_step``, then the simplest model its medium allows
    (:mod:`~seathru_nerfstudio.medium_choice`). The model in use is saved in checkpoints.
    ``auto`` is the default: on the four demo scenes it chose ``none``, ``fog``, ``seathru`` and
    ``seathru``, and lost nothing against a forced ``seathru`` (clear air: 30.9 against 24.9 dB;
    docs/benchmarks.md, session 10)."""
    medium_auto_decision_step: int = 500
    """``auto``: the step at which the medium model is chosen (after ``medium_first_steps``)."""
    medium_auto_evidence_steps: int = 50
    """``auto``: the evidence is the mean over this many steps before the decision."""
    medium_auto_rule: ChoiceRule = field(default_factory=ChoiceRule)
    """``auto``: thresholds of the decision."""
    medium_auto_blend_steps: int = 200
    """``auto``: after the decision the medium moves linearly from the learned ``seathru`` medium
    to the chosen model over this many steps, and the object density is held (no gradient) in
    the meantime, so that the object colour follows instead of the geometry (measured on the clear
    scene, docs/benchmarks.md: switching abruptly or blending alone emptied the geometry). Not
    when ``none`` restarts the object field (``medium_auto_none_restart``)."""
    medium_auto_none_restart: Literal["initial", "first-stage", "off"] = "initial"
    """``auto``: when it chooses ``none``, the object field and the proposal networks go back to
    what they were before training (``initial``; a resumed run: a fresh initialisation) or at the
    end of the first stage (``first-stage``: the SfM geometry, no colour yet), their Adam state is
    cleared, and they train as nerfacto from there, with no blend. What they learned in the
    warm-up makes up for an attenuation that clear air does not have. Measured on the clear demo
    (docs/benchmarks.md, session 10): the blend (``off``) 19.3 dB, ``first-stage`` 27.2 with the
    stale Adam state and 30.1 without, ``initial`` 30.9 (nerfacto 30.8). ``first-stage`` needs
    ``medium_first_steps`` > 0 and the first stage's end in this run: else, and with ``off``, the blend."""
    far_bound_margin: float = 2.0
    """If > 0 and the dataparser gives the scene's far bound (SfM depths, poses_bounds.npy),
    the object field ends at this multiple of it instead of at ``far_plane``: light from much
    farther does not come back through water, and an unbounded field starts as an opaque
    wall behind the open water. 0: nerfacto's ``far_plane``."""
    contraction_at_scene: bool = True
    """The object field's and proposal networks' scene contraction starts at the extent of the
    cameras' view up to the scene's far bound (the dataparser's ``frustum_extent``), not at the unit
    cube the poses are scaled into (:mod:`seathru_nerfstudio.contraction`). With nerfacto's, a
    forward-facing rig's whole scene lies in the contracted shell, where turbid's far surfaces get
    grid cells about 0.5 m deep and come out as thick ramps 4% too far (far-third depth 0.085).
    Alone it walls off turbid's open water (opacity 1.0, clean 20.7 dB), so it goes with
    ``veil_from_open_rays``. Measured with both (docs/benchmarks.md, sessions 23-24, one run each,
    1500 iterations), against the old defaults: turbid 46.35 / 27.63 dB in-medium / clean (45.65 /
    23.70), far third 0.011 (0.085); water 45.93 / 28.60 (44.01 / 26.53); fog 44.57 / 26.12 (41.83 /
    23.50). Off, or without a far bound: nerfacto's."""
    render_from_near_bound: bool = True
    """Renders outside training (evaluation, the viewer, ``ns-render``) start their rays at the
    near bound (the scene's, or ``near_plane`` without one), as training does. nerfstudio starts them at 0, which shows the space in front of
    the near bound: no training ray samples it, so it holds whatever the object field has there
    (measured on the water demo, held-out views: open-water opacity 0.20, PSNR 28.2 dB; with the
    near bound 43.8 dB). Off: a camera closer to the scene than the near bound still sees it."""
    veil_from_open_rays: bool = True
    """The veiling light B_inf learns only from the share of each ray that passes all matter (open
    water), not from the backscatter in front of surfaces, where it trades off against
    ``sigma_bs`` (:func:`~seathru_nerfstudio.rendering.render_seathru`). Without it, under
    ``contraction_at_scene``, turbid's object field walls off the open water and B_inf follows the
    wall (green 0.30 against the true 0.26); with it the open water stays empty (0.08 against 1.00),
    green B_inf is 0.260 and clean 27.6 dB against 20.8 (docs/benchmarks.md, session 23, one run).
    Fog: B_inf exact, clean 26.12 dB against 25.30 without it (session 24). Water: 45.93 / 28.60
    dB against 46.16 / 28.98 without it, less than a seed separates (session 23)."""
    medium_first_steps: int = 200
    """For this many steps the scene is empty and only the veiling light learns (it fits the
    images' average water colour), then the object field starts. The untrained veiling light
    (0.5) is far brighter than dark water; if the object field learns first, it cancels it with a
    black screen in front of the lens (measured: clean image black, open water opaque)."""
    first_stage_geometry: bool = True
    """In the ``medium_first_steps`` stage the object *density* also learns, from the SfM depth
    loss and the empty-space prior (the proposal samplers follow it), while the image still
    shows an empty scene: the object field enters the full model with the capture's geometry
    instead of a faint fog, as WaterSplatting starts from the SfM points. The object colour
    waits for the next stage. Without depth images nothing trains the geometry in that stage
    (the prior alone would only erase it). Measured (docs/benchmarks.md, sessions 4 and 8): it
    keeps the object field from walling off the open water when it starts (water: no wall in 3
    runs of 3; without it a wall in 2 of 4, once kept to step 6000), fixes the oracle-medium run
    (clean 7.1 -> 24.3 dB) and fog's dead clean image (11.1 -> 16.6 dB), +1.4 dB clean on turbid."""
    medium_envelope_quantile: float = 0.0
    """If > 0, in the medium-first stage the densities (``medium_envelope_densities``) also fit
    the backscatter as this lower quantile (e.g. 0.01) of the image at the SfM depths (Sea-thru's dark-pixel estimate,
    :func:`~seathru_nerfstudio.losses.backscatter_envelope_loss`), so that the object field
    starts with a medium estimated from the data instead of ``medium_init_density``;
    attenuation starts equal to backscatter. Measured with the geometry stage (docs/benchmarks.md,
    session 9): on the water demo (seeds 42 and 7) clean 20.3 and 20.8 dB against 19.0 and the
    dim red channel's beta_B within 6% against 54-66% high; on fog (one run) clean 14.1 against
    16.4 dB and the densities further off. Session 12, with ``auto``: it starts the attenuation
    equal to the backscatter, so ``auto`` chose ``uniform`` on water (in-medium 37.1 against 43.6 dB)
    and on turbid. Off by default; with it, force ``medium_model`` unless the water is uniform. 0: off."""
    medium_envelope_densities: Literal["both", "backscatter"] = "both"
    """Which densities fit the envelope (``medium_envelope_quantile``): ``both``, or only the
    backscatter density, the one the envelope measures; the attenuation then keeps its start.
    Measured in a 300-step probe (docs/benchmarks.md, session 16): on water it kept the green
    object colour alive; on fog it did not, because the first stage's veiling light (the mean
    image) is darker than the true one and the envelope's density comes out high under it."""
    backscatter_excess_mult: float = 10.0
    """Weight of :func:`~seathru_nerfstudio.losses.backscatter_excess_loss`, the backscatter above
    the image. A starting medium whose backscatter alone is above the image kills the object
    colour in that channel (a pink ``clean`` image); this term moves the backscatter density
    out of that state instead. It moves only that density: the object geometry is held (else it
    would pull the surfaces nearer) and so is the veiling light, which open water shows directly
    (else it would darken it: water demo, blue B_inf 0.25 against 0.39 by step 300). Measured
    with ``backscatter_excess_steps`` 500 against 0 (docs/benchmarks.md, session 16, one run
    each): turbid 44.7 / 18.3 dB and all 9 medium values within 20% (43.5 / 18.7, 7 of 9), water
    43.5 / 17.6 (43.0 / 17.0), fog 40.4 / 21.5 (40.0 / 22.0). Alone it lowers the clean image of
    the CI scene (48x36 water, 300 steps: 12.9 -> 11.3 dB): the backscatter gets right and the
    attenuation stays high, so the errors no longer cancel. With ``medium_fit_step``, which fixes
    the attenuation, it is the default (session 18). 0: off."""
    backscatter_excess_steps: Optional[int] = 500
    """If set, the backscatter excess loss acts only in the first this many training steps (it
    rescues a dead colour channel early); ``None``: throughout. On a flat rig the attenuation
    and the object colour trade off along a valley, and a one-sided term, however small at the
    truth, walks the medium along it: on fog with ``auto`` (tied to ``fog``) throughout, beta
    fell to 0.86 /m against 1.2 and clean to 16.6 dB (docs/benchmarks.md, session 16)."""
    medium_fit_step: Optional[int] = 500
    """After this training step, set the scene medium's attenuation and backscatter densities to
    their fit to the SfM points' colours across views, given the veiling light learned by then
    (:mod:`seathru_nerfstudio.medium_fit`): gradient descent follows that weak signal slowly. Uses
    the dataparser's SfM observation table (``--sfm-observations``, on by default); without one
    (no SfM depth maps) the densities train on. Applies to ``medium_scope scene`` without
    ``medium_oracle`` only. 500: after the veiling light has settled (1% on the demos; 10-30% off
    at the end of the first stage). The densities are fitted tied as the model in use renders them
    (``auto`` decides first at the same step): ``fog`` one density, ``uniform`` one per channel;
    ``none`` is not fitted. Session 17-18, one run each against the excess term alone:
    water clean 23.9 against 17.6 dB, turbid 20.2 against 18.3 (docs/benchmarks.md). The fit is
    Cauchy-reweighted (silhouette observations see the water behind): session 21, one run each
    against least squares, water 26.5 against 25.9 dB, turbid 23.7 against 21.0. ``None``: off."""
    medium_fit_oracle: Optional[Path] = None
    """Diagnostic: a ``medium.json`` (as for ``medium_oracle``) whose densities replace the fit's
    at ``medium_fit_step`` (which ones: ``medium_fit_oracle_parts``); the veiling light and
    everything before the fit stay learned. Separates the fit's error from the rest of a run."""
    medium_fit_oracle_parts: Literal["both", "attenuation", "backscatter"] = "both"
    """``medium_fit_oracle``: the true ``β_D`` and ``β_B``, or ``β_D`` alone, or ``β_B`` alone (the
    other from the fit)."""
    medium_fit_max_log_error: float = 0.1
    """``medium_fit_step``: a channel keeps its trained densities where the fit's standard error
    of ``ln β_D`` is above this (0.1: about 10%, half the error we accept). On turbid's green the
    least-squares β_D was 41% low, with an error of 0.157; every other channel of the three demos, 0.03-0.07
    (docs/benchmarks.md, session 18). The robust fit (session 21) gives turbid's green 0.055, 8% low."""
    medium_fit_holds: bool = True
    """``medium_fit_step``: the channels the fit replaced keep their fitted densities for the rest
    of training (no gradient); a channel it kept trains on. Off, they train on from the fit, and
    the young object field's errors move them: the fit clears their Adam state, so its first steps
    are full steps (water: blue beta_D 0.97 -> 1.03 /m within 100 steps, which alone caps the clean
    image at 27 dB). Measured (docs/benchmarks.md, session 19, one run each, 1500 iterations):
    water clean 25.3 against 23.9 dB, turbid 20.3 against 20.2, fog 22.2 against 20.4 (with the
    tied fit; session 17's fog without either)."""
    medium_density_hold_steps: int = 0
    """Diagnostic: for this many steps after the object field starts (after ``medium_first_steps``),
    the attenuation and backscatter densities are held (no gradient) while the young object colour
    catches up, so that its early errors cannot move them. 0: off."""
    medium_warmup_steps: int = 0
    """Iterations over which the medium densities ramp up linearly from 0 (clear water); 0: off.
    Experimental: on the demo scene it gave the best in-medium PSNR but baked the water into the
    object field (a far backdrop over the open water, a hazy clean image), so it is off by default."""
    quadrature: Quadrature = "analytic"
    """``analytic``: exact integral of each piecewise-constant interval (reduces exactly to
    the SeaThru formation model). ``paper``: the sec. 4.3 sums as printed."""
    color_space: Literal["linear", "srgb"] = "linear"
    """``linear`` data trains with RawNeRF's relative L2 (the paper's); ``srgb`` data with plain L2.
    The relative loss lets the dim channels count: plain L2 on the linear water demo lost the medium
    (red beta_B 5.9 /m against 0.95, clean 12.9 dB against 19-21; docs/benchmarks.md, session 6)."""
    clear_air_objective: Literal["nerfacto", "seathru"] = "nerfacto"
    """What the ``none`` model trains with (also ``auto`` once it has chosen ``none``). ``nerfacto``:
    nerfacto's plain L2 and no binary prior. The relative loss is there so that the dim channels
    pin down the medium, and the prior so that the object is told apart from the medium; clear air
    has no medium. ``seathru``: the media models' losses."""
    rawnerf_eps: float = 1e-3
    """epsilon of the RawNeRF loss."""
    binary_prior_mult: float = 1e-4
    """Weight of the binary prior on the object transmittance (lambda, the paper's 1e-4) after
    ``binary_prior_early_steps``. From the start it let the object field fill the open water
    before the medium fit, which then read a wrong veiling light (turbid, session 19). After the
    fit it lets faint far surfaces stay (session 20, one run each against 1e-3 throughout: turbid
    far-third depth 0.085 against 0.140, in-medium 45.8 against 44.8 dB; water clean 25.9 against
    25.3 dB; docs/benchmarks.md)."""
    binary_prior_early_mult: Optional[float] = 1e-3
    """The prior's weight before ``binary_prior_early_steps`` (then ``binary_prior_mult``): strong,
    so that the open water stays empty while the first stage learns the veiling light and the
    medium fit reads it. ``None``: ``binary_prior_mult`` from the start. (Session 15 tried the
    other way round, weak first: fog and turbid landed between their two constant weights.)"""
    binary_prior_early_steps: Optional[int] = None
    """Training steps that use ``binary_prior_early_mult``. ``None``: up to ``medium_fit_step``,
    whose fit reads the veiling light that the strong prior keeps clear; with no fit step, the
    early weight throughout."""
    binary_prior_scale: float = 0.1
    """Scale of the two Laplacians of the binary prior."""
    binary_prior_empty_weight: float = 6.0
    """Weight of the prior's mode at ``T = 1`` (empty space) against ``T = 0``: 1 is
    symmetric; the official code uses 6, AkerBP's port 100."""
    # Paper-faithful departures from nerfacto's defaults: no distortion loss, no per-image
    # appearance code (it could explain the water away), no pose refinement.
    distortion_loss_mult: float = 0.0
    use_appearance_embedding: bool = False
    background_color: Literal["random", "last_sample", "black", "white"] = "last_sample"
    """What a ray shows behind the object field when there is no medium: only the ``none`` model
    reads it, and, as nerfacto, takes the colour of the last sample (a distant backdrop). With a
    medium the water is behind everything, and ``clean`` shows black there. (Measured on the
    ``none`` demo, 750 iterations: black 21.8 dB, depth abs-rel 1.32, object opacity 0.41;
    ``last_sample`` 24.7 dB, 0.11, 0.97: black lets dark surfaces stay half transparent.)"""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Refuse settings this model cannot train with, at once and saying why (also called when
        the model is built, for configs changed after construction)."""
        if self.medium_model == "final":  # the name of ``seathru`` in configs saved before it had one
            self.medium_model = "seathru"
        if self.medium_oracle is not None and self.medium_model == "auto":
            # An oracle is the medium: nothing to choose, and a tie would change it (measured: the
            # turbid truth's attenuation and backscatter are within 1.3x, so auto tied it to uniform).
            self.medium_model = "seathru"
        if self.medium_model != "auto" and self.medium_model not in MEDIUM_MODELS:
            raise ValueError(
                f"seathru: unknown medium_model {self.medium_model!r}; expected auto or one of {', '.join(MEDIUM_MODELS)}"
            )
        if self.medium_model == "auto" and not (
            self.medium_first_steps < self.medium_auto_decision_step and 0 < self.medium_auto_evidence_steps
        ):
            raise ValueError(
                "seathru: medium_model auto decides at medium_auto_decision_step "
                f"({self.medium_auto_decision_step}), which must come after medium_first_steps "
                f"({self.medium_first_steps}), from medium_auto_evidence_steps ({self.medium_auto_evidence_steps}) > 0 steps"
            )
        if self.medium_fit_oracle is not None and (self.medium_fit_step is None or self.medium_oracle is not None):
            raise ValueError("seathru: medium_fit_oracle replaces the fit of medium_fit_step: set that step, without medium_oracle")
        if not self.medium_fit_max_log_error > 0:  # NaN fails too
            raise ValueError(f"seathru: medium_fit_max_log_error must be > 0 (got {self.medium_fit_max_log_error})")
        early_weight = self.binary_prior_early_mult
        early_steps = self.binary_prior_early_steps
        if (early_steps is not None and early_steps < 0) or not (early_weight is None or early_weight >= 0):  # NaN fails too
            raise ValueError(
                "seathru: binary_prior_early_steps must be >= 0 and binary_prior_early_mult None or >= 0 "
                f"(got {self.binary_prior_early_steps} and {early_weight})"
            )
        if self.predict_normals:
            raise ValueError(
                "seathru: predict_normals=True is not supported: SeathruModel renders no normals, so "
                "nerfacto's normal losses would have nothing to read. Leave --pipeline.model.predict-normals False."
            )


def read_true_medium(path: Path) -> dict:
    """``beta_D``, ``beta_B`` (1/world unit) and ``B_inf`` of a ``medium.json`` as ``seathru-synth``
    writes it, three numbers each; a ``ValueError`` naming the file if it is not one."""
    try:
        truth = json.loads(Path(path).read_text())
        values = {key: [float(v) for v in truth[key]] for key in ("beta_D", "beta_B", "B_inf")}
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise ValueError(f"seathru: {path} is not a medium.json with beta_D, beta_B and B_inf: {error!r}") from error
    if any(len(v) != 3 or not all(math.isfinite(x) for x in v) for v in values.values()):
        raise ValueError(f"seathru: {path}: beta_D, beta_B and B_inf must be three finite numbers each")
    return values


class SeathruModel(NerfactoModel):
    """nerfacto's object field rendered through a scattering medium (Levy et al. 2023)."""

    config: SeathruModelConfig

    def populate_modules(self) -> None:
        self.config.check()
        # nerfacto builds LPIPS here, which downloads AlexNet: build it only if it is on disk.
        with metrics.offline_lpips():
            super().populate_modules()
        self.train_step: Optional[int] = None
        """The trainer's step while training (a callback sets it); None in a loaded model."""
        self.last_diagnostics: Dict[str, torch.Tensor] = {}
        """:func:`diagnostics.decomposition` of the last training batch (also in the metrics)."""
        metadata = self.kwargs.get("metadata") or {}
        self.world_scale = float(metadata.get(SCALE_KEY, 1.0))
        """Scene units per world unit (metre): a density per scene unit times this is per metre."""
        if not (math.isfinite(self.world_scale) and self.world_scale > 0):
            raise ValueError(
                f"seathru: the dataparser's scale ({SCALE_KEY}) is {self.world_scale}; it must be finite and "
                "positive (do all cameras sit at one point?)"
            )
        self.medium_field = self._build_medium()
        # read now, so a bad file fails at set-up and not at medium_fit_step
        self.fit_oracle = read_true_medium(self.config.medium_fit_oracle) if self.config.medium_fit_oracle else None
        code = UNDECIDED if self.config.medium_model == "auto" else MEDIUM_MODELS.index(self.config.medium_model)
        self.register_buffer("medium_model_code", torch.tensor(code, dtype=torch.long))
        """Index in ``MEDIUM_MODELS`` of the medium model in use (``UNDECIDED``: ``auto`` before its
        decision); a buffer, so that checkpoints record the model ``auto`` chose."""
        self.register_buffer("medium_model_step", torch.tensor(-1, dtype=torch.long))
        """The step at which the blend from ``seathru`` to ``auto``'s choice starts (-1: no blend)."""
        self.register_buffer("densities_fitted", torch.zeros(6, dtype=torch.bool))
        """Which of ``beta_D`` (RGB) then ``beta_B`` (RGB) ``medium_fit_holds`` holds at their fit."""
        self.auto_evidence: List[MediumEvidence] = []
        """``auto``: the evidence of the steps before the decision."""
        self.first_stage_object: Optional[Dict[str, Dict[str, torch.Tensor]]] = None
        """``auto`` before its decision: copies of the object field's and the proposal networks'
        state to restart ``none`` from (``medium_auto_none_restart``)."""
        if self.config.medium_model == "auto" and self.config.medium_auto_none_restart == "initial":
            self.first_stage_object = self._object_state()
        if not self.config.object_view_dependent:
            self.field.direction_encoding = FixedDirectionEncoding(self.field.direction_encoding)
        self.contraction_radius = 1.0
        """Scene units at which the hash grids' contraction starts (1: nerfacto's)."""
        if self.config.contraction_at_scene and EXTENT_KEY in metadata:
            self.contraction_radius = max(1.0, float(metadata[EXTENT_KEY]))
            contraction = ContractionBeyond(self.contraction_radius)
            self.field.spatial_distortion = contraction
            for network in self.proposal_networks:
                network.spatial_distortion = contraction
        self.far_range: Optional[float] = (
            float(metadata["far_plane"]) / self.world_scale if "far_plane" in metadata else None
        )
        """The scene's far bound in world units (``None``: no SfM bounds); ``auto`` weighs the
        medium's attenuation-backscatter gap over it."""
        if "near_plane" in metadata:
            # The scene's own bounds (seathru-data: poses_bounds.npy; nerfstudio-data: the SfM
            # depths), with margins; the renderer adds the water in front of the near and behind
            # the far bound in closed form, so nothing is lost.
            far = self.config.far_plane
            if self.config.far_bound_margin > 0 and "far_plane" in metadata:
                far = self.config.far_bound_margin * float(metadata["far_plane"])
            self.collider = NearFarCollider(near_plane=0.9 * float(metadata["near_plane"]), far_plane=far)
        # Renders start where training rays start (the near bound above, or nerfacto's near_plane).
        self.collider.reset_near_plane = not self.config.render_from_near_bound
        # Viewer controls (no parameters; never applied in training).
        self.viewer_controls = viewer.SeathruViewerControls(linear_data=self.config.color_space == "linear")
        self.medium_controls_enabled = True
        """Renders outside training take the viewer's water density and veiling light (identity at
        their defaults); SeathruPipeline turns this off while it evaluates."""

    def _build_medium(self):
        if self.config.medium_oracle is not None:
            truth = read_true_medium(self.config.medium_oracle)
            if self.config.medium_oracle_learns:
                densities = [b / self.world_scale for b in [*truth["beta_D"], *truth["beta_B"]]]
                return SceneMedium(init_density=densities, init_rgb=truth["B_inf"])
            # 1/world unit -> 1/scene unit
            return FixedMedium(
                rgb=truth["B_inf"],
                sigma_attn=[b / self.world_scale for b in truth["beta_D"]],
                sigma_bs=[b / self.world_scale for b in truth["beta_B"]],
            )
        if self.config.medium_scope == "scene":
            return SceneMedium(init_density=self._initial_medium_density())
        return MediumField(
            num_layers=self.config.medium_num_layers,
            hidden_dim=self.config.medium_hidden_dim,
            sh_levels=self.config.medium_sh_levels,
            init_density=self._initial_medium_density(),
            implementation=self.config.implementation,
        )

    def _initial_medium_density(self) -> float:
        """The learned medium's starting densities, per scene unit (``medium_init_optical_depth``)."""
        spread = (self.kwargs.get("metadata") or {}).get(RANGE_SPREAD_KEY)
        if self.config.medium_init_optical_depth > 0 and spread is not None and spread.mean_range > 0:
            density = self.config.medium_init_optical_depth / (spread.mean_range * self.world_scale)
            if math.isfinite(density):  # a degenerate (subnormal) mean range would give inf
                return density
        return self.config.medium_init_density

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        # Checkpoints from before the medium model was recorded: the model of the config.
        state_dict.setdefault(prefix + "medium_model_code", self.medium_model_code.clone())
        state_dict.setdefault(prefix + "medium_model_step", self.medium_model_step.clone())
        state_dict.setdefault(prefix + "densities_fitted", torch.zeros_like(self.densities_fitted))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def medium_model(self) -> str:
        """The medium model in use: the config's, or what ``auto`` chose (``seathru`` before)."""
        code = int(self.medium_model_code)
        return "seathru" if code == UNDECIDED else MEDIUM_MODELS[code]

    @property
    def fits_medium(self) -> bool:
        """Whether ``medium_fit_step`` applies: it fits the constants of one water body, so not a
        medium of the ray direction, nor a fixed oracle."""
        config = self.config
        return config.medium_fit_step is not None and config.medium_scope == "scene" and config.medium_oracle is None

    @property
    def medium_blend(self) -> float:
        """How far the medium has moved from ``seathru`` to the chosen model since ``auto``
        decided: 0 -> 1 over ``medium_auto_blend_steps``; 1 without a decision to blend from,
        and in a loaded model (no training step)."""
        since = int(self.medium_model_step)
        if since < 0 or self.train_step is None or self.config.medium_auto_blend_steps <= 0:
            return 1.0
        return min(1.0, max(0.0, (self.train_step - since) / self.config.medium_auto_blend_steps))

    @property
    def medium_ramp(self) -> float:
        """Scale on the medium densities: 0 -> 1 over the warm-up, 1 afterwards (and when a
        checkpoint is loaded for eval or rendering)."""
        warmup = self.config.medium_warmup_steps
        if warmup <= 0 or self.train_step is None:
            return 1.0
        return min(1.0, self.train_step / warmup)

    @property
    def binary_prior_weight(self) -> float:
        """The binary prior's weight at this training step (``binary_prior_mult`` outside training)."""
        early = self.config.binary_prior_early_mult
        if early is None or self.train_step is None:
            return self.config.binary_prior_mult
        switch = self.config.binary_prior_early_steps
        if switch is None:
            switch = self.config.medium_fit_step  # None too: no fit to wait for, the early weight throughout
        if switch is None or self.train_step < switch:
            return early
        return self.config.binary_prior_mult

    @property
    def backscatter_excess_active(self) -> bool:
        """True while the backscatter excess loss applies (``backscatter_excess_mult``, ``_steps``)."""
        if self.config.backscatter_excess_mult <= 0:
            return False
        limit = self.config.backscatter_excess_steps
        return limit is None or self.train_step is None or self.train_step < limit

    @property
    def densities_held(self) -> bool:
        """True in the ``medium_density_hold_steps`` training steps after the object field starts."""
        start = self.config.medium_first_steps
        return (
            self.training
            and self.train_step is not None
            and start <= self.train_step < start + self.config.medium_density_hold_steps
        )

    @property
    def object_frozen(self) -> bool:
        """True in the first ``medium_first_steps`` training steps, where only the medium learns.

        With a fixed medium (``medium_oracle``) only if the geometry learns in it
        (``first_stage_geometry``): otherwise there would be nothing to learn. Never for the
        ``none`` model: clear air has no medium to learn first."""
        if self.medium_model == "none":  # clear air: nerfacto from step 0
            return False
        medium_learns = any(p.requires_grad for p in self.medium_field.parameters())
        return (
            (medium_learns or self.config.first_stage_geometry)
            and self.training
            and self.train_step is not None
            and self.train_step < self.config.medium_first_steps
        )

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)

        if self.config.diagnostics_every > 0:
            callbacks.append(
                TrainingCallback(
                    where_to_run=[TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                    update_every_num_iters=self.config.diagnostics_every,
                    func=self._print_diagnostics,
                )
            )

        def set_step(step: int) -> None:
            self.train_step = step

        optimizers = getattr(training_callback_attributes, "optimizers", None)
        if self.config.medium_model == "auto":
            callbacks.append(
                TrainingCallback(
                    where_to_run=[TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                    update_every_num_iters=1,
                    func=lambda step: self._decide_medium_model(step, optimizers),
                )
            )
        if self.fits_medium:  # after auto's decision at the same step: the fit ties as the model chosen
            callbacks.append(
                TrainingCallback(
                    where_to_run=[TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                    update_every_num_iters=1,
                    func=lambda step: self._fit_medium(step, optimizers),
                )
            )

        callbacks.append(
            TrainingCallback(
                where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION],
                update_every_num_iters=1,
                func=set_step,
            )
        )
        return callbacks

    def _fit_medium(self, step: int, optimizers: Optional[Optimizers] = None) -> None:
        """``medium_fit_step``: replace the densities by their fit to the SfM observations under the
        veiling light learned so far; ``optimizers``: the trainer's, whose density state is cleared."""
        if step + 1 != self.config.medium_fit_step or not self.fits_medium:
            return
        table = (self.kwargs.get("metadata") or {}).get(SFM_OBSERVATIONS_KEY)
        if table is None or table.num_observations == 0:
            CONSOLE.print(
                f"[bold yellow]seathru step {step}: medium_fit_step has no SfM observations to fit "
                "(no SfM depth maps, or the dataparser's --sfm-observations False); the densities train on"
            )
            return
        if self.medium_model == "none":
            CONSOLE.print(f"[bold]seathru step {step}: no medium to fit (medium model none)")
            return
        medium = self.medium_field
        with torch.no_grad():
            densities = torch.nn.functional.softplus(medium.density_raw.double()) * self.world_scale
            veil = torch.sigmoid(medium.rgb_logit.double())
        fit = fit_densities(  # tied as the model renders them
            torch.from_numpy(table.ranges),
            torch.from_numpy(table.colours),
            veil,
            densities[:3],
            densities[3:],
            tie=self.medium_model,
        )
        uncertain = fit.attenuation_log_error > self.config.medium_fit_max_log_error
        show = lambda values: ", ".join(f"{float(v):.3g}" for v in values)  # noqa: E731
        oracle_parts = self.config.medium_fit_oracle_parts if self.fit_oracle is not None else None
        if uncertain.all() and oracle_parts is None:  # nothing to replace: leave the parameters and their Adam state alone
            CONSOLE.print(
                f"[bold]seathru step {step}: medium fit to {table.num_observations} SfM observations kept the "
                f"trained densities (standard error of ln beta_D {show(fit.attenuation_log_error)})"
            )
            return
        beta_d = torch.where(uncertain, densities[:3], fit.attenuation)
        beta_b = torch.where(uncertain, densities[3:], fit.backscatter)
        replaced_d, replaced_b = ~uncertain, ~uncertain
        if oracle_parts is not None:  # diagnostic: the truth in place of the fit (and held like it)
            truth = self.fit_oracle
            if oracle_parts != "backscatter":
                beta_d, replaced_d = torch.tensor(truth["beta_D"], dtype=beta_d.dtype), torch.ones_like(uncertain)
            if oracle_parts != "attenuation":
                beta_b, replaced_b = torch.tensor(truth["beta_B"], dtype=beta_b.dtype), torch.ones_like(uncertain)
            CONSOLE.print(f"[bold]seathru step {step}: medium_fit_oracle: the true densities ({oracle_parts}) replace the fit")
        fitted = torch.cat([beta_d, beta_b]) / self.world_scale
        with torch.no_grad():
            medium.density_raw.copy_(torch.tensor([inverse_softplus(float(d)) for d in fitted]))
        if optimizers is not None and "medium_density" in optimizers.optimizers:
            optimizers.optimizers["medium_density"].state.clear()  # Adam's moments were for the old values
        if self.config.medium_fit_holds:
            self.densities_fitted.copy_(torch.cat([replaced_d, replaced_b]).to(self.densities_fitted.device))
        CONSOLE.print(
            f"[bold]seathru step {step}: medium fitted to {table.num_observations} SfM observations ({self.medium_model} tie)[/] "
            f"(residual {fit.residual:.3g}): beta_D {show(densities[:3])} -> {show(beta_d)} /m, "
            f"beta_B {show(densities[3:])} -> {show(beta_b)} /m, under B_inf {show(veil)}; "
            f"standard error of ln beta_D {show(fit.attenuation_log_error)}"
            + (f", kept the trained values of channel(s) {uncertain.nonzero().flatten().tolist()}" if uncertain.any() else "")
        )

    def _decide_medium_model(self, step: int, optimizers: Optional[Optimizers] = None) -> None:
        """``auto``: at ``medium_auto_decision_step``, keep the simplest medium model the warm-up's
        medium allows. Only the tying of the medium changes: the object field and the medium's
        parameters carry on as they are (a tied model starts from the mean of what was learned),
        except that ``none`` restarts the object field from the end of the first stage
        (``medium_auto_none_restart``), which is why this also runs at that step; ``optimizers``:
        the trainer's, whose state of the restarted parameter groups is cleared."""
        if int(self.medium_model_code) != UNDECIDED:
            return
        if step + 1 == self.config.medium_first_steps and self.config.medium_auto_none_restart == "first-stage":
            self.first_stage_object = self._object_state()
        if step + 1 < self.config.medium_auto_decision_step:
            return
        evidence = self._mean_evidence()
        if evidence is None:
            return  # resumed right before the decision: gather the evidence first
        chosen, reason = choose_medium_model(evidence, self.config.medium_auto_rule)
        self.medium_model_code.fill_(MEDIUM_MODELS.index(chosen))
        if chosen == "none" and self.first_stage_object is not None:
            self.field.load_state_dict(self.first_stage_object["field"])
            self.proposal_networks.load_state_dict(self.first_stage_object["proposal_networks"])
            for group in ("fields", "proposal_networks"):
                if optimizers is not None and group in optimizers.optimizers:
                    optimizers.optimizers[group].state.clear()  # Adam restarts with the parameters
            start = "the end of the first stage" if self.config.medium_auto_none_restart == "first-stage" else "its initial state"
            reason += f"; the object field restarts from {start}"
        elif chosen != "seathru":  # the warm-up's own model: nothing to blend
            self.medium_model_step.fill_(step + 1)
        self.first_stage_object = None
        self.auto_evidence.clear()
        CONSOLE.print(f"[bold]seathru step {step}: medium model auto -> {chosen}[/] ({reason})")

    def _object_state(self) -> Dict[str, Dict[str, torch.Tensor]]:
        """Copies of the object field's and the proposal networks' parameters and buffers."""
        return {
            "field": {name: value.detach().clone() for name, value in self.field.state_dict().items()},
            "proposal_networks": {
                name: value.detach().clone() for name, value in self.proposal_networks.state_dict().items()
            },
        }

    def _record_evidence(self, values: Dict[str, torch.Tensor]) -> None:
        """``auto``: keep this step's medium diagnostics if the decision is near."""
        step = self.train_step
        if (
            int(self.medium_model_code) != UNDECIDED
            or step is None
            or step < self.config.medium_auto_decision_step - self.config.medium_auto_evidence_steps
        ):
            return

        def rgb(name: str):
            return tuple(float(values[f"medium_{name}_{c}"]) for c in diagnostics.CHANNELS)

        self.auto_evidence.append(
            MediumEvidence(
                backscatter_share=float(values["backscatter_share"]),
                beta_D=rgb("beta_D"),
                beta_B=rgb("beta_B"),
                B_inf=rgb("B_inf"),
            )
        )

    def _mean_evidence(self) -> Optional[MediumEvidence]:
        """The mean of the recorded evidence, over every process of a distributed run (so that
        all of them choose the same model); ``None`` if nothing was recorded."""
        if not self.auto_evidence:
            return None
        rows = torch.tensor(
            [[e.backscatter_share, *e.beta_D, *e.beta_B, *e.B_inf] for e in self.auto_evidence], dtype=torch.float64
        )
        mean = rows.mean(dim=0)
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            mean = mean.to(self.device)
            torch.distributed.all_reduce(mean)
            mean = mean.cpu() / torch.distributed.get_world_size()
        values = [float(v) for v in mean]
        return MediumEvidence(
            backscatter_share=values[0],
            beta_D=tuple(values[1:4]),
            beta_B=tuple(values[4:7]),
            B_inf=tuple(values[7:10]),
            far_range=self.far_range,
        )

    def _print_diagnostics(self, step: int) -> None:
        values = self.last_diagnostics
        if values:
            CONSOLE.print(f"[dim]seathru step {step}:[/] {diagnostics.format_line(values)}")

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        param_groups = super().get_param_groups()
        # "medium_density": the densities of a per-scene medium, slower than its colour (see
        # SceneMedium.density_parameters); "medium": the rest (all of a per-ray MLP). An oracle has none.
        density = list(getattr(self.medium_field, "density_parameters", list)())
        rest = [p for p in self.medium_field.parameters() if all(p is not d for d in density)]
        if rest:
            param_groups["medium"] = rest
        if density:
            param_groups["medium_density"] = density
        return param_groups

    def get_outputs(self, ray_bundle: RayBundle, with_medium: bool = True):
        """The outputs contract of a batch of rays. ``with_medium=False``: the object outputs only
        (:data:`OBJECT_OUTPUTS`, ``prop_depth_<i>``), without evaluating the medium."""
        if self.training:
            self.camera_optimizer.apply_to_raybundle(ray_bundle)
        ray_samples, weights_list, ray_samples_list = self.proposal_sampler(ray_bundle, density_fns=self.density_fns)
        field_outputs = self.field.forward(ray_samples)
        geometry = None
        if self.object_frozen and self.config.first_stage_geometry:
            # The object geometry alone (not rendered): its weights for the depth loss and the
            # proposal samplers, its transmittance for the empty-space prior.
            geometry = object_weights(field_outputs[FieldHeadNames.DENSITY], ray_samples.deltas)[:2]
        if self.object_frozen:
            # No object yet: every ray shows the veiling light, which fits the images' average
            # water colour; the densities get no gradient from a scene that is not there.
            field_outputs = {name: value.detach() for name, value in field_outputs.items()}
            field_outputs[FieldHeadNames.DENSITY] = torch.zeros_like(field_outputs[FieldHeadNames.DENSITY])
        if self.training and self.medium_blend < 1.0:
            # auto, just after its decision: the geometry holds while the colour follows the medium
            # (measured on the clear scene: a switch to none brightens the objects; their colour,
            # saturated under the invented attenuation, follows slowly, and the loss emptied the
            # geometry instead: opacity 0.89 -> 0.42, depth error 0.19 -> 1.1 within 200 steps).
            field_outputs[FieldHeadNames.DENSITY] = field_outputs[FieldHeadNames.DENSITY].detach()
        if self.config.use_gradient_scaling:
            field_outputs = scale_gradients_by_distance_squared(field_outputs, ray_samples)
        if not with_medium or self.clear_air:
            render = self._render_clear_air(field_outputs, ray_samples)
            outputs = self._collect_outputs(
                ray_bundle, ray_samples, weights_list, ray_samples_list, render, clear_medium(ray_bundle.directions), geometry
            )
            if not with_medium:
                for name in WATER_OUTPUTS + MEDIUM_OUTPUTS:
                    outputs.pop(name)
            return outputs
        medium = self.medium(ray_bundle.directions)  # once per ray
        densities_for_envelope = None
        if self.object_frozen and self.config.medium_envelope_quantile > 0:
            densities_for_envelope = torch.cat([medium.sigma_attn, medium.sigma_bs], dim=-1)
        if self.object_frozen or self.densities_held:
            # An empty scene shows exactly c_med on every ray, whatever the densities: keep round-off
            # gradients (which Adam would scale up to full steps) off them.
            medium = MediumOutputs(rgb=medium.rgb, sigma_attn=medium.sigma_attn.detach(), sigma_bs=medium.sigma_bs.detach())
        ramp = self.medium_ramp
        if ramp < 1.0:
            medium = MediumOutputs(rgb=medium.rgb, sigma_attn=medium.sigma_attn * ramp, sigma_bs=medium.sigma_bs * ramp)
        render = render_seathru(
            object_rgb=field_outputs[FieldHeadNames.RGB],
            object_density=field_outputs[FieldHeadNames.DENSITY],
            starts=ray_samples.frustums.starts,
            deltas=ray_samples.deltas,
            medium_rgb=medium.rgb,
            sigma_attn=medium.sigma_attn,
            sigma_bs=medium.sigma_bs,
            quadrature=self.config.quadrature,
            veil_from_open_rays=self.config.veil_from_open_rays,
        )
        outputs = self._collect_outputs(
            ray_bundle, ray_samples, weights_list, ray_samples_list, render, medium, geometry, densities_for_envelope
        )
        if self.training and self.backscatter_excess_active and not self.object_frozen:
            held = render_seathru(
                object_rgb=torch.zeros_like(field_outputs[FieldHeadNames.RGB]),
                object_density=field_outputs[FieldHeadNames.DENSITY].detach(),
                starts=ray_samples.frustums.starts,
                deltas=ray_samples.deltas,
                medium_rgb=medium.rgb.detach(),
                sigma_attn=medium.sigma_attn,
                sigma_bs=medium.sigma_bs,
                quadrature=self.config.quadrature,
            )
            outputs["backscatter_geometry_held"] = held.backscatter
        return outputs

    @property
    def clear_air(self) -> bool:
        """True when the model in use is ``none`` (and any blend to it is over): no medium at all."""
        return self.medium_model == "none" and self.medium_blend >= 1.0

    def medium(self, directions: torch.Tensor) -> MediumOutputs:
        """The medium of rays with these unit directions as rendered now: the model in use (tied,
        or zero for ``none``), blended from ``seathru`` just after ``auto`` decided, and outside
        training changed by the viewer's water controls. Clear air evaluates no network."""
        if self.clear_air:
            return clear_medium(directions)
        learned = self.medium_field(directions)
        if self.training:  # medium_fit_holds, before any tie; all-False holds nothing (no host sync to ask)
            held_attn, held_bs = self.densities_fitted[:3], self.densities_fitted[3:]
            learned = MediumOutputs(
                rgb=learned.rgb,
                sigma_attn=torch.where(held_attn, learned.sigma_attn.detach(), learned.sigma_attn),
                sigma_bs=torch.where(held_bs, learned.sigma_bs.detach(), learned.sigma_bs),
            )
        medium = clear_medium(directions) if self.medium_model == "none" else tie(learned, self.medium_model)
        blend = self.medium_blend
        if blend < 1.0:  # auto, just after its decision
            medium = blend_media(learned, medium, blend)
        if not self.training and self.medium_controls_enabled:
            medium = self.viewer_controls.medium(medium)  # the viewer's water density and colour
        return medium

    def _render_clear_air(self, field_outputs, ray_samples) -> SeathruRender:
        """The ``none`` model: nerfacto's rendering (its weights ``T_i (1 - e^{-sigma_i delta_i})``,
        from :func:`object_weights` in one pass with the transmittance the binary prior reads, and
        nerfstudio's ``RGBRenderer``), with the contract's medium outputs at their exact values:
        ``rgb = direct = clean``, zero backscatter. Also the object-only pass of a medium model
        (``get_outputs(with_medium=False)``), whose ``clean`` has a black background."""
        weights, transmittance, _ = object_weights(field_outputs[FieldHeadNames.DENSITY], ray_samples.deltas)
        # Behind the object field: nerfacto's background in clear air; black for the clean image of
        # a medium model (rendered here without its medium), as render_seathru's clean.
        background = None if self.clear_air else "black"
        rgb = self.renderer_rgb(rgb=field_outputs[FieldHeadNames.RGB], weights=weights, background_color=background)
        accumulation = self.renderer_accumulation(weights=weights)
        return SeathruRender(
            rgb=rgb,
            direct=rgb,
            backscatter=torch.zeros_like(rgb),
            clean=rgb,
            weights=weights,
            transmittance=transmittance,
            accumulation=accumulation,
        )

    def _collect_outputs(
        self,
        ray_bundle: RayBundle,
        ray_samples,
        weights_list: list,
        ray_samples_list: list,
        render: SeathruRender,
        medium: MediumOutputs,
        geometry: Optional[tuple] = None,
        densities_for_envelope: Optional[torch.Tensor] = None,
    ) -> Dict[str, torch.Tensor]:
        """The outputs contract of one batch of rays, from a render and its (tied) medium;
        ``geometry``: the first stage's object weights and transmittance, for the losses."""
        weights_list.append(render.weights if geometry is None else geometry[0])
        ray_samples_list.append(ray_samples)
        with torch.no_grad():
            depth = self.renderer_depth(weights=render.weights, ray_samples=ray_samples)
        outputs = {
            "rgb": render.rgb,
            "clean": render.clean,
            "direct": render.direct,
            "backscatter": render.backscatter,
            "depth": depth,
            "expected_depth": self.renderer_expected_depth(weights=render.weights, ray_samples=ray_samples),
            "accumulation": render.accumulation,
            "medium_rgb": medium.rgb,
            "medium_attenuation": medium.sigma_attn,
            "medium_backscatter": medium.sigma_bs,
        }
        if self.training:
            outputs["weights_list"] = weights_list
            outputs["ray_samples_list"] = ray_samples_list
            outputs["transmittance"] = render.transmittance if geometry is None else geometry[1]
            if "directions_norm" in (ray_bundle.metadata or {}):
                outputs["directions_norm"] = ray_bundle.metadata["directions_norm"]
            if densities_for_envelope is not None:
                outputs["medium_densities_for_envelope"] = densities_for_envelope
        if not self.training:  # no loss reads them
            for i in range(self.config.num_proposal_iterations):
                outputs[f"prop_depth_{i}"] = self.renderer_depth(weights=weights_list[i], ray_samples=ray_samples_list[i])
        return outputs

    @torch.no_grad()
    def get_outputs_for_camera_ray_bundle(self, camera_ray_bundle: RayBundle) -> Dict[str, torch.Tensor]:
        """A whole image. While training, nerfstudio's render of every output. Outside training,
        :class:`~seathru_nerfstudio.lazy_outputs.LazyOutputs`: the display outputs of
        :mod:`seathru_nerfstudio.viewer` first (nerfstudio's viewer opens on the first output),
        then the linear ones, each computed when it is first read: a view of ``clean`` or of
        ``depth`` never evaluates the medium, a medium map never evaluates the object field, and
        ``rgb`` brings the object outputs along (one pass over the field) but not the medium maps."""
        if self.training:
            return super().get_outputs_for_camera_ray_bundle(camera_ray_bundle)
        prop_depths = tuple(f"prop_depth_{i}" for i in range(self.config.num_proposal_iterations))
        names = viewer.DISPLAY_OUTPUTS + WATER_OUTPUTS + OBJECT_OUTPUTS + MEDIUM_OUTPUTS + prop_depths

        @torch.no_grad()  # read later, outside this method's no_grad (ns-render reads with grad on)
        def compute(name: str, outputs) -> Dict[str, torch.Tensor]:
            if name in viewer.DISPLAY_OUTPUTS:
                return {name: self.viewer_controls.display_output(name, outputs)}
            if name in MEDIUM_OUTPUTS:
                return self._render_medium_maps(camera_ray_bundle)
            return self._render_image(camera_ray_bundle, with_medium=name in WATER_OUTPUTS)

        return LazyOutputs(names, compute)

    def _render_image(self, camera_ray_bundle: RayBundle, with_medium: bool) -> Dict[str, torch.Tensor]:
        """nerfstudio's chunked whole-image render (``eval_num_rays_per_chunk`` rays at a time),
        of the water and object outputs, or (``with_medium=False``) of the object outputs only."""
        keep = (WATER_OUTPUTS if with_medium else ()) + OBJECT_OUTPUTS
        keep += tuple(f"prop_depth_{i}" for i in range(self.config.num_proposal_iterations))
        chunks: Dict[str, List[torch.Tensor]] = {name: [] for name in keep}
        for bundle in self._chunks(camera_ray_bundle):
            bundle = self.collider(bundle) if self.collider is not None else bundle
            outputs = self.get_outputs(bundle, with_medium=with_medium)
            for name in keep:
                chunks[name].append(outputs[name].to(camera_ray_bundle.origins.device))
        return self._images(camera_ray_bundle, chunks)

    def _render_medium_maps(self, camera_ray_bundle: RayBundle) -> Dict[str, torch.Tensor]:
        """The per-ray medium maps, from the ray directions alone (no object field)."""
        chunks: Dict[str, List[torch.Tensor]] = {name: [] for name in MEDIUM_OUTPUTS}
        for bundle in self._chunks(camera_ray_bundle):
            medium = self.medium(bundle.directions.to(self.device))
            for name, value in zip(MEDIUM_OUTPUTS, (medium.rgb, medium.sigma_attn, medium.sigma_bs)):
                chunks[name].append(value.to(camera_ray_bundle.origins.device))
        return self._images(camera_ray_bundle, chunks)

    def _chunks(self, camera_ray_bundle: RayBundle):
        """An image's rays in row-major chunks of ``eval_num_rays_per_chunk``, on the model's device."""
        step = self.config.eval_num_rays_per_chunk
        for start in range(0, len(camera_ray_bundle), step):
            yield camera_ray_bundle.get_row_major_sliced_ray_bundle(start, start + step).to(self.device)

    @staticmethod
    def _images(camera_ray_bundle: RayBundle, chunks: Dict[str, List[torch.Tensor]]) -> Dict[str, torch.Tensor]:
        height, width = camera_ray_bundle.origins.shape[:2]
        return {name: torch.cat(values).view(height, width, -1) for name, values in chunks.items()}

    def get_metrics_dict(self, outputs, batch) -> Dict[str, torch.Tensor]:
        metrics_dict = super().get_metrics_dict(outputs, batch)
        if self.training:
            values = diagnostics.decomposition(outputs, batch.get("gt_depth"), self.world_scale)
            if self.config.medium_model == "auto":
                self._record_evidence(values)
            # The model in use, as its index in MEDIUM_MODELS (-1: auto, not decided yet).
            values["medium_model"] = self.medium_model_code.detach().clone()
            metrics_dict.update(values)  # TensorBoard: "Train Metrics Dict/..."
            self.last_diagnostics = values
        return metrics_dict

    def get_loss_dict(self, outputs, batch, metrics_dict=None):
        # nerfacto's terms (interlevel, distortion, camera), then the paper's colour loss.
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        nerfacto_objective = self.clear_air and self.config.clear_air_objective == "nerfacto"
        if self.config.color_space == "linear" and not nerfacto_objective:
            image = batch["image"][..., :3].to(self.device)
            loss_dict["rgb_loss"] = rawnerf_loss(outputs["rgb"], image, eps=self.config.rawnerf_eps)
        no_geometry_yet = self.object_frozen and "depth_image" not in batch and self.config.depth_source == "sfm"
        prior_weight = self.binary_prior_weight
        if self.training and prior_weight > 0 and not nerfacto_objective and not no_geometry_yet:
            loss_dict["binary_prior_loss"] = prior_weight * binary_transmittance_loss(
                outputs["transmittance"],
                scale=self.config.binary_prior_scale,
                empty_weight=self.config.binary_prior_empty_weight,
            )
        if "backscatter_geometry_held" in outputs:
            loss_dict["backscatter_excess_loss"] = self.config.backscatter_excess_mult * backscatter_excess_loss(
                outputs["backscatter_geometry_held"], batch["image"][..., :3].to(self.device), eps=self.config.rawnerf_eps
            )
        if "medium_densities_for_envelope" in outputs and "depth_image" in batch:
            loss_dict["backscatter_envelope_loss"] = self._envelope_loss(outputs, batch)
        if self.training and self.config.depth_loss_mult > 0:
            loss = self._depth_loss(outputs, batch)
            if loss is not None:
                loss_dict["depth_loss"] = self.config.depth_loss_mult * loss
            elif not getattr(self, "_warned_no_depth", False):
                self._warned_no_depth = True
                CONSOLE.print(
                    "[yellow]seathru: the dataset has no depth images (depth_file_path), so no depth loss: "
                    "seathru-process-data writes sparse SfM depths, seathru-synth writes them too"
                )
        if self.object_frozen and not any(loss.requires_grad for loss in loss_dict.values()):
            raise ValueError(
                "seathru: nothing learns in the first stage: the medium is fixed (medium_oracle) and the "
                "dataset has no depth images for first_stage_geometry. Set --pipeline.model.medium-first-steps 0."
            )
        return loss_dict

    def _envelope_loss(self, outputs, batch) -> torch.Tensor:
        """Medium-first stage: attenuation and backscatter densities both fit the backscatter
        envelope at the SfM ranges, under the veiling light learned so far (held fixed here)."""
        z_depth = batch["depth_image"].to(self.device)  # scene units; 0 = unknown
        ray_range = z_depth * outputs.get("directions_norm", torch.ones_like(z_depth))
        image = batch["image"][..., :3].to(self.device)
        veil = outputs["medium_rgb"].detach()
        sigma_attn, sigma_bs = outputs["medium_densities_for_envelope"].split(3, dim=-1)
        quantile = self.config.medium_envelope_quantile
        loss = backscatter_envelope_loss(image, ray_range, veil, sigma_bs, quantile)
        if self.config.medium_envelope_densities == "both":
            loss = loss + backscatter_envelope_loss(image, ray_range, veil, sigma_attn, quantile)
        return loss

    def _depth_loss(self, outputs, batch) -> Optional[torch.Tensor]:
        """nerfacto's DS-NeRF depth loss on the object weights, where a depth is known
        (``None``: the dataset has no depth images)."""
        if self.config.depth_source == "ground-truth":
            if "gt_depth" not in batch:
                raise KeyError("depth_source='ground-truth' needs a dataset with ground_truth/depth (seathru-synth)")
            truth = batch["gt_depth"].to(self.device)  # range, scene units; inf = open water
            is_euclidean = True
        else:
            if "depth_image" not in batch:
                return None
            truth = batch["depth_image"].to(self.device)  # z-depth, scene units; 0 = unknown
            is_euclidean = False
        hit = torch.isfinite(truth)
        termination_depth = torch.where(hit, truth, torch.zeros_like(truth))
        directions_norm = outputs.get("directions_norm", torch.ones_like(truth))
        loss = depth_loss(
            weights=outputs["weights_list"][-1],
            ray_samples=outputs["ray_samples_list"][-1],
            termination_depth=termination_depth,
            predicted_depth=outputs["expected_depth"],
            # nerfstudio's DS-NeRF loss divides by 2 * sigma: it takes the variance.
            sigma=self._depth_kernel_variance(outputs, termination_depth, directions_norm, is_euclidean),
            directions_norm=directions_norm,
            is_euclidean=is_euclidean,
            depth_loss_type=DepthLossType.DS_NERF,
        )
        # nerfstudio averages over every ray of the batch; average over the rays that have a
        # depth instead, so that the weight does not depend on how sparse the SfM points are.
        known = (hit & (truth > 0)).float()
        loss = loss * known.numel() / torch.clamp(known.sum(), min=1.0)
        if not is_euclidean:
            return loss
        # Open water: nothing to hit, so no object opacity.
        open_water = (~hit).float()
        return loss + torch.sum(outputs["accumulation"] * open_water) / max(1.0, float(open_water.numel()))

    def _depth_kernel_variance(
        self, outputs, termination_depth: torch.Tensor, directions_norm: torch.Tensor, is_euclidean: bool
    ) -> torch.Tensor:
        """The depth loss's variance in scene units squared: one value, or one per ray.
        ``termination_depth`` as the depth loss takes it (finite; z-depth unless ``is_euclidean``)."""
        sigma_floor = self.config.depth_sigma * self.world_scale
        if not self.config.depth_sigma_follows_sampling:
            return torch.tensor(sigma_floor**2, device=self.device)
        frustums = outputs["ray_samples_list"][-1].frustums
        ray_range = termination_depth if is_euclidean else termination_depth * directions_norm
        return depth_kernel_variance(frustums.starts, frustums.ends, ray_range, sigma_floor)

    def get_image_metrics_and_images(
        self, outputs: Dict[str, torch.Tensor], batch: Dict[str, torch.Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        gt_rgb = self.renderer_rgb.blend_background(batch["image"].to(self.device))
        predicted_rgb = outputs["rgb"].clamp(0.0, 1.0)
        truth = {key: batch[key].to(self.device) for key in ("gt_clean", "gt_depth") if key in batch}
        metrics_dict = metrics.view_metrics(
            outputs, gt_rgb, lpips=self.lpips, linear_data=self.config.color_space == "linear", **truth
        )

        depth = colormaps.apply_depth_colormap(outputs["depth"], accumulation=outputs["accumulation"])
        images_dict = {
            "img": torch.cat([gt_rgb, predicted_rgb], dim=1),
            "clean": outputs["clean"].clamp(0.0, 1.0),
            "backscatter": outputs["backscatter"].clamp(0.0, 1.0),
            "depth": depth,
            "accumulation": colormaps.apply_colormap(outputs["accumulation"]),
        }
        return metrics_dict, images_dict


class FixedDirectionEncoding(torch.nn.Module):
    """An encoding that always encodes one fixed direction: a colour head fed by it is
    view-independent (Lambertian), with nerfacto's field left as it is."""

    def __init__(self, encoding: torch.nn.Module) -> None:
        super().__init__()
        self.encoding = encoding

    def get_out_dim(self) -> int:
        return self.encoding.get_out_dim()

    def forward(self, directions: torch.Tensor) -> torch.Tensor:
        fixed = torch.zeros_like(directions[:1])
        fixed[..., 2] = 1.0
        return self.encoding(fixed).expand(directions.shape[0], -1)

