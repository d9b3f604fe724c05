"""SeaThru-NeRF as a nerfacto subclass: nerfacto's object field and proposal sampling, a medium
(:mod:`~seathru_nerfstudio.medium_field`) and the scattering renderer of
:mod:`~seathru_nerfstudio.rendering`. This module holds nerfstudio's hooks; each concern they call
sits in a module named for it (docs/architecture.md):

* options: :mod:`~seathru_nerfstudio.model_config`; the schedule: :mod:`~seathru_nerfstudio.phases`;
* nerfacto's field fitted to the capture: :mod:`~seathru_nerfstudio.object_field`;
* ``auto``'s decision and the medium fit, as callbacks: :mod:`~seathru_nerfstudio.medium_choice`,
  :mod:`~seathru_nerfstudio.medium_fit`; the oracles: :mod:`~seathru_nerfstudio.oracles`;
* losses: :mod:`~seathru_nerfstudio.losses`; whole-image renders:
  :mod:`~seathru_nerfstudio.camera_rendering`.
"""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Tuple

import torch
from torch.nn import Parameter

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.model_components.losses import scale_gradients_by_distance_squared
from nerfstudio.models.nerfacto import NerfactoModel
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio import diagnostics, export, metrics, viewer
from seathru_nerfstudio.camera_rendering import MEDIUM_OUTPUTS, WATER_OUTPUTS, lazy_camera_outputs
from seathru_nerfstudio.losses import (
    backscatter_excess_loss,
    binary_transmittance_loss,
    rawnerf_loss,
    sfm_depth_loss,
)
from seathru_nerfstudio.medium_choice import UNDECIDED, AutoMediumChoice
from seathru_nerfstudio.medium_field import MEDIUM_MODELS, MediumField, MediumOutputs, SceneMedium, blend_media, clear_medium
from seathru_nerfstudio.medium_field import level_axes, level_components, sin_elevation, tie
from seathru_nerfstudio.medium_start import OpenWaterColour, apply_density_caps
from seathru_nerfstudio.medium_fit import apply_medium_fit
from seathru_nerfstudio.metadata_keys import RANGE_SPREAD_KEY, SCALE_KEY, VERTICAL_KEY
from seathru_nerfstudio.model_config import ResearchConfig, SeathruModelConfig
from seathru_nerfstudio.object_field import FixedDirectionEncoding, scene_collider, scene_contraction_radius, set_contraction
from seathru_nerfstudio.oracles import oracle_medium, read_true_medium
from seathru_nerfstudio.phases import TrainingPhases
from seathru_nerfstudio.rendering import SeathruRender, object_weights, render_seathru
from seathru_nerfstudio.surface_veil import SurfaceVeil

__all__ = ["ResearchConfig", "SeathruModel", "SeathruModelConfig", "UNDECIDED"]


class SeathruModel(NerfactoModel):
    """nerfacto's object field rendered through a scattering medium (Levy et al. 2023)."""

    config: SeathruModelConfig

    def populate_modules(self) -> None:
        self.config.check()
        with metrics.offline_lpips():  # nerfacto builds LPIPS here: only from weights on disk
            super().populate_modules()
        metadata = self.kwargs.get("metadata") or {}
        research = self.config.research
        self.train_step: Optional[int] = None
        """The trainer's step while training (a callback sets it); None in a loaded model."""
        self.last_diagnostics: Dict[str, torch.Tensor] = {}
        """:func:`diagnostics.decomposition` of the last training batch (also in the metrics)."""
        self.world_scale = float(metadata.get(SCALE_KEY, 1.0))
        """Scene units per world unit (metre): a density per scene unit times this is per metre."""
        if not (math.isfinite(self.world_scale) and self.world_scale > 0):
            raise ValueError(
                f"seathru: the dataparser's scale ({SCALE_KEY}) is {self.world_scale}; it must be finite and "
                "positive (do all cameras sit at one point?)"
            )
        self.fit_oracle = read_true_medium(research.medium_fit_oracle) if research.medium_fit_oracle else None
        self.register_buffer("vertical", torch.tensor(metadata.get(VERTICAL_KEY, (0.0, 0.0, 1.0))).float(), persistent=False)
        """The scene frame's unit up (:func:`~seathru_nerfstudio.vertical.scene_vertical`): elevations are measured along it."""
        self.register_buffer("level_axes", level_axes(self.vertical), persistent=False)
        """:func:`~seathru_nerfstudio.medium_field.level_axes` of :attr:`vertical`: where the open rays look round the horizon."""
        self.medium_field = self._build_medium(metadata)
        self.open_water_colour = OpenWaterColour()  # the first stage's open rays: the veil from its end on
        self.surface_veil_reader = SurfaceVeil()  # the surface rays before the fit: the veil in front of them
        code = UNDECIDED if self.config.medium_model == "auto" else MEDIUM_MODELS.index(self.config.medium_model)
        self.register_buffer("medium_model_code", torch.tensor(code, dtype=torch.long))
        """Index in ``MEDIUM_MODELS`` of the model in use (``UNDECIDED``: ``auto`` before its decision)."""
        self.register_buffer("medium_model_step", torch.tensor(-1, dtype=torch.long))
        """The step at which the blend from ``seathru`` to ``auto``'s choice starts (-1: no blend)."""
        self.register_buffer("densities_fitted", torch.zeros(6, dtype=torch.bool))
        """Which of ``beta_D`` (RGB) then ``beta_B`` (RGB) hold at their fit."""
        self.register_buffer("fit_log_error", torch.full((3,), -1.0, dtype=torch.float64))
        """The medium fit's standard error of ``ln beta_D`` per channel (-1: no fit yet; finite, as
        every checkpointed value must be)."""
        self.register_buffer("fit_backscatter_log_error", torch.full((3,), -1.0, dtype=torch.float64))
        """The same for ``ln beta_B`` (-1: no fit yet, or a checkpoint written before it was kept)."""
        self.register_buffer("backscatter_veil_sensitivity", torch.zeros(3, dtype=torch.float64))
        """``d ln beta_B / d ln B_inf`` at the fit (:func:`~seathru_nerfstudio.medium_fit.veil_sensitivity`)."""
        self.auto_choice = AutoMediumChoice(self) if self.config.medium_model == "auto" else None
        self.field.direction_encoding = FixedDirectionEncoding(self.field.direction_encoding)
        self.contraction_radius = 1.0
        """Scene units at which the hash grids' contraction starts (1: nerfacto's)."""
        self.fit_object_field_to_medium_model()
        self.register_load_state_dict_post_hook(lambda model, _keys: model.fit_object_field_to_medium_model())
        self.far_range: Optional[float] = (
            float(metadata["far_plane"]) / self.world_scale if "far_plane" in metadata else None
        )
        """The scene's far bound in world units (``None``: no SfM bounds)."""
        collider = scene_collider(metadata, self.config.far_plane, self.config.far_bound_margin)
        self.collider = collider if collider is not None else self.collider
        self.collider.reset_near_plane = not self.config.render_from_near_bound
        self.viewer_controls = viewer.SeathruViewerControls(linear_data=self.config.color_space == "linear")
        self.medium_controls_enabled = True
        """Renders outside training take the viewer's water controls; SeathruPipeline turns this off to evaluate."""

    def fit_object_field_to_medium_model(self) -> None:
        """The object field for the medium model in use, set again whenever it changes and after a checkpoint
        loads (:mod:`~seathru_nerfstudio.object_field`): with a medium, Lambertian colour and the contraction at the
        scene's extent (:func:`~seathru_nerfstudio.object_field.scene_contraction_radius`); in clear air (``none``),
        nerfacto's view-dependent colour and contraction (``object_view_dependent`` set: that colour always or never)."""
        view_dependent = self.config.object_view_dependent
        self.field.direction_encoding.fixed = not (self.medium_model == "none" if view_dependent is None else view_dependent)
        metadata = self.kwargs.get("metadata") or {}
        radius = 1.0 if self.medium_model == "none" else scene_contraction_radius(metadata)
        if radius != self.contraction_radius:
            self.contraction_radius = set_contraction(self.field, self.proposal_networks, radius)

    def _build_medium(self, metadata) -> torch.nn.Module:
        research = self.config.research
        if research.medium_oracle is not None:
            return oracle_medium(read_true_medium(research.medium_oracle), self.world_scale, research.medium_oracle_learns)
        density = research.medium_init_density
        spread = metadata.get(RANGE_SPREAD_KEY)
        if self.config.medium_init_optical_depth > 0 and spread is not None and spread.mean_range > 0:
            from_range = self.config.medium_init_optical_depth / (spread.mean_range * self.world_scale)
            density = from_range if math.isfinite(from_range) else density  # a subnormal range would give inf
        if self.config.medium_scope == "scene":
            scene_medium = SceneMedium(init_density=density)
            scene_medium.set_vertical(self.vertical)
            return scene_medium
        return MediumField(
            num_layers=self.config.medium_num_layers,
            hidden_dim=self.config.medium_hidden_dim,
            sh_levels=self.config.medium_sh_levels,
            init_density=density,
            implementation=self.config.implementation,
        )

    @property
    def phases(self) -> TrainingPhases:
        """The schedule at the current training step (:mod:`~seathru_nerfstudio.phases`)."""
        return TrainingPhases(self.config, self.train_step, int(self.medium_model_step))

    @property
    def medium_model(self) -> str:
        """The medium model in use: the config's, or what ``auto`` chose (``seathru`` before)."""
        code = int(self.medium_model_code)
        return "seathru" if code == UNDECIDED else MEDIUM_MODELS[code]

    @property
    def fits_medium(self) -> bool:
        """Whether ``medium_fit_step`` applies: to the constants of one water body, not to an oracle."""
        config = self.config
        return config.medium_fit_step is not None and config.medium_scope == "scene" and config.research.medium_oracle is None

    @property
    def medium_blend(self) -> float:
        return self.phases.medium_blend

    @property
    def object_frozen(self) -> bool:
        """In the first stage of a medium model's training: the image shows an empty scene."""
        return self.training and self.medium_model != "none" and self.phases.first_stage

    @property
    def veil_held(self) -> bool:
        """In training after a first stage whose SfM-trained geometry read the open water's colour into the scene medium's veil (never an oracle's)."""
        depths = (self.kwargs.get("metadata") or {}).get("depth_filenames") and self.config.research.medium_oracle is None
        return bool(self.training and self.phases.after_first_stage and self.config.medium_scope == "scene" and depths)

    @property
    def clear_air(self) -> bool:
        """True when the model in use is ``none`` (and any blend to it is over): no medium at all."""
        return self.medium_model == "none" and self.medium_blend >= 1.0

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        optimizers = getattr(training_callback_attributes, "optimizers", None)
        after = [TrainingCallbackLocation.AFTER_TRAIN_ITERATION]
        if self.config.diagnostics_every > 0:
            callbacks.append(TrainingCallback(after, self._print_diagnostics, update_every_num_iters=self.config.diagnostics_every))
        if self.auto_choice is not None:
            before = [TrainingCallbackLocation.BEFORE_TRAIN_ITERATION]
            callbacks.append(TrainingCallback(before, self.auto_choice.clear_air_before_training))
            callbacks.append(TrainingCallback(after, lambda step: self.auto_choice.after_step(step, optimizers)))
        callbacks.append(TrainingCallback(after, lambda step: apply_density_caps(self, step, optimizers)))
        if self.fits_medium:  # after auto's decision at the same step: the fit ties as the model chosen
            callbacks.append(TrainingCallback(after, lambda step: apply_medium_fit(self, step, optimizers)))

        def set_step(step: int) -> None:
            self.train_step = step

        callbacks.append(TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], set_step))
        return callbacks

    def _print_diagnostics(self, step: int) -> None:
        if self.last_diagnostics:
            CONSOLE.print(f"[dim]seathru step {step}:[/] {diagnostics.format_line(self.last_diagnostics)}")

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        param_groups = super().get_param_groups()
        # "medium_density": a scene medium's densities, slower than its colour; "medium": the rest.
        density = list(getattr(self.medium_field, "density_parameters", list)())
        rest = [p for p in self.medium_field.parameters() if all(p is not d for d in density)]
        if rest:
            param_groups["medium"] = rest
        if density:
            param_groups["medium_density"] = density
        return param_groups

    def get_outputs(self, ray_bundle: RayBundle, with_medium: bool = True):
        """The outputs of a batch of rays. ``with_medium=False``: the object outputs only, without
        evaluating the medium."""
        if self.training:
            self.camera_optimizer.apply_to_raybundle(ray_bundle)
        ray_samples, weights_list, ray_samples_list = self.proposal_sampler(ray_bundle, density_fns=self.density_fns)
        field_outputs = self.field.forward(ray_samples)
        geometry = None
        if self.object_frozen:
            # First stage: the object geometry alone (its weights for the depth loss and the proposal
            # samplers, its transmittance for the prior), while every ray shows the veiling light.
            geometry = object_weights(field_outputs[FieldHeadNames.DENSITY], ray_samples.deltas)[:2]
            field_outputs = {name: value.detach() for name, value in field_outputs.items()}
            field_outputs[FieldHeadNames.DENSITY] = torch.zeros_like(field_outputs[FieldHeadNames.DENSITY])
        if self.training and self.medium_blend < 1.0:  # auto's blend: the geometry holds, the colour follows
            field_outputs[FieldHeadNames.DENSITY] = field_outputs[FieldHeadNames.DENSITY].detach()
        if self.config.use_gradient_scaling:
            field_outputs = scale_gradients_by_distance_squared(field_outputs, ray_samples)
        if not with_medium or self.clear_air:
            render = self._render_clear_air(field_outputs, ray_samples)
            medium = clear_medium(ray_bundle.directions)
            outputs = self._collect_outputs(ray_bundle, ray_samples, weights_list, ray_samples_list, render, medium, geometry)
            for name in () if with_medium else WATER_OUTPUTS + MEDIUM_OUTPUTS:
                outputs.pop(name)
            return outputs
        medium = self.medium(ray_bundle.directions)  # once per ray
        if self.object_frozen:
            # An empty scene shows exactly c_med whatever the densities: keep round-off gradients off them.
            medium = MediumOutputs(rgb=medium.rgb, sigma_attn=medium.sigma_attn.detach(), sigma_bs=medium.sigma_bs.detach())
        elif self.veil_held:
            medium = MediumOutputs(rgb=medium.rgb.detach(), sigma_attn=medium.sigma_attn, sigma_bs=medium.sigma_bs)
        # The veil brightens looking up because the far water is higher, in brighter light; the backscatter
        # in front of a surface keeps the level veil's rate (rendering.depth_lit_backscatter_density).
        veil_gain = self.medium_field.rendered_veil_gain(ray_bundle.directions) if isinstance(self.medium_field, SceneMedium) else None
        render = render_seathru(
            object_rgb=field_outputs[FieldHeadNames.RGB], object_density=field_outputs[FieldHeadNames.DENSITY],
            starts=ray_samples.frustums.starts, deltas=ray_samples.deltas, medium_rgb=medium.rgb,
            sigma_attn=medium.sigma_attn, sigma_bs=medium.sigma_bs, quadrature=self.config.quadrature,
            veil_from_open_rays=True, veil_gain=veil_gain, surface_veil=self._surface_veil(medium.rgb),
        )
        outputs = self._collect_outputs(ray_bundle, ray_samples, weights_list, ray_samples_list, render, medium, geometry)
        if self.training and self.phases.backscatter_excess_active and not self.object_frozen:
            # The backscatter alone, the geometry and the veil held: the excess loss moves sigma_bs only.
            held = render_seathru(
                object_rgb=torch.zeros_like(field_outputs[FieldHeadNames.RGB]),
                object_density=field_outputs[FieldHeadNames.DENSITY].detach(),
                starts=ray_samples.frustums.starts,
                deltas=ray_samples.deltas,
                medium_rgb=medium.rgb.detach(),
                sigma_attn=medium.sigma_attn,
                sigma_bs=medium.sigma_bs,
                quadrature=self.config.quadrature,
                veil_gain=veil_gain,
                surface_veil=self._surface_veil(medium.rgb),
            )
            outputs["backscatter_geometry_held"] = held.backscatter
        return outputs

    def _surface_veil(self, medium_rgb: torch.Tensor) -> Optional[torch.Tensor]:
        """The scene medium's veil in front of the surfaces over the open water's (:mod:`~seathru_nerfstudio.surface_veil`), per ray."""
        share = getattr(self.medium_field, "surface_veil", None)
        return None if share is None else share.to(medium_rgb).expand_as(medium_rgb)

    def medium(self, directions: torch.Tensor) -> MediumOutputs:
        """The medium of rays with these unit directions as rendered now: the model in use (tied, or
        zero for ``none``), blended from ``seathru`` just after ``auto`` decided, the fitted densities
        held in training, and outside training changed by the viewer's water controls."""
        if self.clear_air:
            return clear_medium(directions)
        learned = self.medium_field(directions)
        if self.training:  # the fitted densities hold; all-False holds nothing (no host sync to ask)
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
            medium = self.viewer_controls.medium(medium)
        return medium

    def _render_clear_air(self, field_outputs, ray_samples) -> SeathruRender:
        """nerfacto's rendering with the medium outputs at their exact values (``rgb = direct =
        clean``, zero backscatter): the ``none`` model, and the object-only pass of a medium model,
        whose ``clean`` has a black background (as :func:`render_seathru`'s)."""
        weights, transmittance, _ = object_weights(field_outputs[FieldHeadNames.DENSITY], ray_samples.deltas)
        background = None if self.clear_air else "black"
        rgb = self.renderer_rgb(rgb=field_outputs[FieldHeadNames.RGB], weights=weights, background_color=background)
        accumulation = self.renderer_accumulation(weights=weights)
        zeros = torch.zeros_like(rgb)
        return SeathruRender(rgb=rgb, direct=rgb, backscatter=zeros, clean=rgb, weights=weights, transmittance=transmittance, accumulation=accumulation)

    def _collect_outputs(self, ray_bundle, ray_samples, weights_list, ray_samples_list, render, medium, geometry=None):
        """The outputs of one batch of rays from a render and its medium; ``geometry``: the first
        stage's object weights and transmittance, for the losses."""
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
            outputs["direction_up"] = sin_elevation(ray_bundle.directions, self.vertical)
            outputs["direction_level"] = level_components(ray_bundle.directions, self.level_axes)
            if "directions_norm" in (ray_bundle.metadata or {}):
                outputs["directions_norm"] = ray_bundle.metadata["directions_norm"]
        else:  # no loss reads them
            for i in range(self.config.num_proposal_iterations):
                outputs[f"prop_depth_{i}"] = self.renderer_depth(weights=weights_list[i], ray_samples=ray_samples_list[i])
        return outputs

    @torch.no_grad()
    def get_outputs_for_camera_ray_bundle(self, camera_ray_bundle: RayBundle) -> Dict[str, torch.Tensor]:
        """A whole image: while training, nerfstudio's render of every output; outside training,
        :func:`~seathru_nerfstudio.camera_rendering.lazy_camera_outputs`."""
        if self.training:
            return super().get_outputs_for_camera_ray_bundle(camera_ray_bundle)
        return lazy_camera_outputs(self, camera_ray_bundle)

    def get_rgba_image(self, outputs: Dict[str, torch.Tensor], output_name: str = "rgb") -> torch.Tensor:
        """nerfstudio's exporters (``ns-export``): the clean colour with the viewer's display transform,
        and the object opacity as alpha (:func:`~seathru_nerfstudio.export.get_rgba_image`)."""
        return export.get_rgba_image(self, outputs, output_name)

    def get_metrics_dict(self, outputs, batch) -> Dict[str, torch.Tensor]:
        metrics_dict = super().get_metrics_dict(outputs, batch)
        if self.training:
            values = diagnostics.decomposition(outputs, batch.get("gt_depth"), self.world_scale)
            if self.auto_choice is not None:
                self.auto_choice.record(values, self.train_step)
            values["medium_model"] = self.medium_model_code.detach().clone()  # -1: auto, not decided yet
            metrics_dict.update(values)  # TensorBoard: "Train Metrics Dict/..."
            self.last_diagnostics = values
        return metrics_dict

    def get_loss_dict(self, outputs, batch, metrics_dict=None):
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)  # nerfacto's terms
        research = self.config.research
        image = batch["image"][..., :3].to(self.device)
        if self.config.color_space == "linear" and not self.clear_air:  # clear air: nerfacto's L2
            loss_dict["rgb_loss"] = rawnerf_loss(outputs["rgb"], image, eps=research.rawnerf_eps)
        no_geometry_yet = self.object_frozen and "depth_image" not in batch and research.depth_source == "sfm"
        if self.training and self.object_frozen and not no_geometry_yet and self.phases.reads_open_water:
            past_last = outputs["transmittance"][..., -1, :] - outputs["weights_list"][-1][..., -1, :]  # T past the last sample
            self.open_water_colour.add(image, past_last, outputs["direction_up"], outputs["direction_level"])
        if self.training and self.veil_held and self.phases.reads_surface_veil:
            self.surface_veil_reader.add(image, outputs["medium_rgb"], outputs["depth"], outputs["accumulation"])
        prior_weight = self.phases.binary_prior_weight
        if self.training and prior_weight > 0 and not self.clear_air and not no_geometry_yet:
            loss_dict["binary_prior_loss"] = prior_weight * binary_transmittance_loss(
                outputs["transmittance"], scale=research.binary_prior_scale, empty_weight=self.config.binary_prior_empty_weight
            )
        if "backscatter_geometry_held" in outputs:
            loss_dict["backscatter_excess_loss"] = research.backscatter_excess_mult * backscatter_excess_loss(
                outputs["backscatter_geometry_held"], image, eps=research.rawnerf_eps
            )
        depth_weight = self.config.clear_air_depth_loss_mult if self.clear_air else self.config.depth_loss_mult
        if self.training and depth_weight > 0:
            loss = self._depth_loss(outputs, batch)
            if loss is not None:
                loss_dict["depth_loss"] = depth_weight * loss
            elif not getattr(self, "_warned_no_depth", False):
                self._warned_no_depth = True
                CONSOLE.print(
                    "[yellow]seathru: the dataset has no depth images (depth_file_path), so no depth loss: "
                    "seathru-process-data writes sparse SfM depths, seathru-synth writes them too"
                )
        if self.object_frozen and not any(loss.requires_grad for loss in loss_dict.values()):
            raise ValueError(
                "seathru: nothing learns in the first stage: the medium is fixed (research.medium_oracle) and the "
                "dataset has no depth images. Set --pipeline.model.medium-first-steps 0."
            )
        return loss_dict

    def _depth_loss(self, outputs, batch) -> Optional[torch.Tensor]:
        """The DS-NeRF depth loss on the SfM depths (or, ``research.depth_source ground-truth``, on a
        synthetic scene's dense true range); ``None`` if the dataset has no depth images."""
        if self.config.research.depth_source == "ground-truth":
            if "gt_depth" not in batch:
                raise KeyError("research.depth_source ground-truth needs a dataset with ground-truth depth (seathru-synth)")
            known, is_euclidean = batch["gt_depth"].to(self.device), True  # range, scene units; inf = open water
        elif "depth_image" in batch:
            known, is_euclidean = batch["depth_image"].to(self.device), False  # z-depth, scene units; 0 = unknown
        else:
            return None
        return sfm_depth_loss(
            weights=outputs["weights_list"][-1],
            ray_samples=outputs["ray_samples_list"][-1],
            expected_depth=outputs["expected_depth"],
            known_depth=known,
            directions_norm=outputs.get("directions_norm", torch.ones_like(known)),
            sigma_floor=self.config.research.depth_sigma * self.world_scale,
            is_euclidean=is_euclidean,
            accumulation=outputs["accumulation"],
        )

    def get_image_metrics_and_images(
        self, outputs: Dict[str, torch.Tensor], batch: Dict[str, torch.Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        gt_rgb = self.renderer_rgb.blend_background(batch["image"].to(self.device))
        truth = {key: batch[key].to(self.device) for key in ("gt_clean", "gt_depth") if key in batch}
        metrics_dict = metrics.view_metrics(
            outputs, gt_rgb, lpips=self.lpips, linear_data=self.config.color_space == "linear", **truth
        )
        images_dict = {
            "img": torch.cat([gt_rgb, outputs["rgb"].clamp(0.0, 1.0)], dim=1),
            "clean": outputs["clean"].clamp(0.0, 1.0),
            "backscatter": outputs["backscatter"].clamp(0.0, 1.0),
            "depth": colormaps.apply_depth_colormap(outputs["depth"], accumulation=outputs["accumulation"]),
            "accumulation": colormaps.apply_colormap(outputs["accumulation"]),
        }
        return metrics_dict, images_dict
