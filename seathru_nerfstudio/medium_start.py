"""The medium where the object field enters: the veiling light read from the open water, and the
densities bounded by the SfM observations.

**The veiling light.** ``B∞`` is the colour of a ray that meets nothing. The first stage renders an
empty scene, so gradient descent there teaches ``B∞`` the mean image, the objects included (the
formula-drawn water demo: 0.093, 0.184, 0.328 at step 199 against 0.07, 0.2, 0.39). But the first
stage also trains the object *geometry* from the SfM depths and the empty-space prior. Over its second
half, :class:`OpenWaterColour` averages the colour of the training rays that geometry leaves open
(:func:`is_open_water`: transmittance above 95% of the clearest rays'), and at its end that mean
becomes ``B∞``, held from then on (``SeathruModel.veil_held``). Light falls from above, so the open water brightens looking up: the
veil of rays looking up rises along the least-squares line of the colour over ``sin(elevation)`` of the
open rays above the level plane, from where that line passes the held mean (held too; never falls:
:meth:`OpenWaterColour.rise`, :meth:`~seathru_nerfstudio.medium_field.SceneMedium.set_veil_rise`).
Path-traced coastal water, seed 7: 32.11 dB in the medium against 30.37 with one constant veil
(docs/history.md, 2026-11-28 (eba0fe7)). Round the horizon the veil changes by the slopes of the
least-squares plane of the same rays' colour over ``(sin(elevation), h1, h2)``, ``h`` the ray's level
components (:meth:`OpenWaterColour.across`,
:meth:`~seathru_nerfstudio.medium_field.SceneMedium.set_veil_across`): under a sun 45° high and 100°
round from behind the rig, the open water is 12–30% brighter per unit of ``h1`` towards it, and the
held-out image in the medium rose from 31.88 to 32.31 dB (docs/history.md, 2026-12-06 (the veil round
the horizon)).
A rise fitted to all the open rays, unlike a maximum over groups of them, is not moved by one group
that holds object colour (the 48×36 water check's open water filled under the maximum). Learned on
after entry instead, from the rays the object field leaves open, the veil climbs as that field fills
the darker open water (path-traced coastal: blue 0.41 at entry, 0.61 at step 1500, best fit 0.44),
and the densities fitted under it at step 500 follow it (docs/history.md, 2026-11-28).

A surface at range ``z`` (world units) shows, per channel,

    I = J e^{-β_D z} + B∞ (1 - e^{-β_B z}),   0 <= J <= 1,

``J`` being the object colour, a sigmoid. Both ends of its range bound a density:

* ``J >= 0``: no observation lies below the backscatter, ``B∞ (1 - e^{-β_B z}) <= I``, so

      β_B <= b(I, z) = -ln(1 - I / B∞) / z      (no bound where I >= B∞);

* ``J <= 1``: the attenuated colour can reach what is left above the backscatter,
  ``e^{-β_D z} >= I - B∞ (1 - e^{-β_B z})``, so

      β_D <= d(I, z) = -ln(I - B∞ (1 - e^{-β_B z})) / z      (no bound where I <= the backscatter).

Each SfM observation gives both bounds; the darkest surfaces at every range give the tightest
``b``, the brightest the tightest ``d``. Sea-thru (Akkaynak & Treibitz, CVPR 2019, sec. 4.3) reads
the backscatter from the darkest 1% of the pixels; here the same 1% is taken of the
per-observation bounds, so that noise on a few pixels does not set them. ``β_B`` is bounded
first, then ``β_D`` under the bounded backscatter.

Why this exists: the first stage learns ``B∞`` from an empty scene while the densities wait at
their start (``medium_init_optical_depth``, an optical depth of 3 at the mean SfM range). Where that
start puts the backscatter above the darker surfaces, the image asks for a negative object colour;
the colour's sigmoid saturates at 0 within about ten steps of the object field's entry and never
returns (its gradient vanishes, and with it the attenuation's). Path-traced coastal water
(``seathru-pathtrace``, β_B 0.31, 0.14, 0.08 /m) started at 0.45 /m in every channel, and the object
colour was dead by step 210 (docs/history.md, 2026-11-27). Where the start attenuates more than
the brightest surfaces allow, the colour saturates at 1 instead, and the object density gives way
to the veiling light behind it: clear air started at 0.45 /m, where nothing attenuates, and its
surfaces rendered half transparent (object opacity 0.54 at step 400, J 3.8 dB). The bounds are
applied once, at the end of the first stage, under the veiling light learned there, and only lower
a density. On the path-traced presets the attenuation bound lies at or above the single-scattering
truth except in turbid water, where multiple scattering brightens the far surfaces (0.44, 0.25,
0.37 against 0.55, 0.35, 0.50 /m); on the formula-drawn water demo it lies above the truth
(1.62, 1.48, 1.13 against 1.3, 1.2, 0.9).

Units: ranges in world units, densities per world unit, colours linear.
"""

from __future__ import annotations

from typing import Any, Optional, Tuple

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio.metadata_keys import SFM_OBSERVATIONS_KEY
from seathru_nerfstudio.phases import TrainingPhases

DENSITY_FLOOR = 1e-6
"""The cap never goes below this (per world unit): a softplus parameter cannot hold 0 exactly."""

OPEN_SHARE = 0.95
"""A ray counts as open water when the first stage's geometry lets through this share of what the
clearest rays of its batch let through (:func:`is_open_water`): a hard threshold, since a silhouette ray
that is partly open carries the object's colour (weighted by its open share instead, the 48×36 water
demo's veil ended 8% off; docs/history.md, 2026-11-28)."""

CLEAREST_QUANTILE = 0.99
"""The clearest rays of a batch: this quantile of their open shares (an actual ray's, not interpolated)."""

LEAST_CLEAREST = 0.8
"""The clearest rays are taken to let through at least this much: where none does (no open water in
view), only rays above ``OPEN_SHARE × LEAST_CLEAREST`` count, and those are open."""

FEATURES = 4
"""The open water's colour is read over ``(1, up, h1, h2)``: a plane in the ray direction (:meth:`OpenWaterColour.across`)."""

MIN_OPEN_FRACTION = 0.01
"""Fewer open rays than this share of those seen, and the veil learned in the first stage stays."""


def is_open_water(open_share: Float[Tensor, "N"]) -> Bool[Tensor, "N"]:
    """The rays the first stage's geometry leaves open: an open share (transmittance past the last
    sample, 0–1) above :data:`OPEN_SHARE` times the batch's clearest (:data:`CLEAREST_QUANTILE`, at
    least :data:`LEAST_CLEAREST`).

    Why relative: the first stage's geometry can keep a faint haze on every ray. On path-traced
    turbid water with seed 7 it let through at most 0.94 of any ray (0.99 with seed 42), so a fixed
    0.95 found 0.1% of the rays open where 37% of the pixels are open water, and the veil was not
    read (docs/history.md, 2026-11-29). Where the clearest rays are clear the threshold is 0.95 as
    before."""
    if open_share.numel() == 0:
        return torch.zeros_like(open_share, dtype=torch.bool)
    clearest = torch.quantile(open_share.float(), CLEAREST_QUANTILE, interpolation="higher")
    return open_share > OPEN_SHARE * torch.clamp(clearest, min=LEAST_CLEAREST)


class OpenWaterColour(torch.nn.Module):
    """The colour of the training rays the first stage's geometry leaves open, and how it changes
    with their elevation ``up = sin(elevation)`` (along the scene's vertical, :mod:`~seathru_nerfstudio.vertical`): the
    sums of a least-squares line.

    The sums are the module's extra state, so a checkpoint holds them and a run killed in the first
    stage and resumed reads the same veil as one that was not. They are not buffers: DDP would
    overwrite every process's own sums with the first process's before each step. Only that first
    process writes checkpoints, so only it takes the sums back (the others start from none)."""

    def __init__(self) -> None:
        super().__init__()
        self.total = torch.zeros(3, dtype=torch.float64)
        self.total_up_colour = torch.zeros(3, dtype=torch.float64)
        self.total_up = torch.zeros(2, dtype=torch.float64)  # sums of up and up^2
        self.above_gram = torch.zeros(FEATURES, FEATURES, dtype=torch.float64)
        """Over the open rays above the level plane (``up > 0``): ``Σ f fᵀ`` with ``f = (1, up, h1, h2)``, ``h``
        the ray's :func:`~seathru_nerfstudio.medium_field.level_components` (``[0, 0]`` is their count)."""
        self.above_colour = torch.zeros(FEATURES, 3, dtype=torch.float64)
        """``Σ f colourᵀ`` over the same rays."""
        self.level_extent = torch.full((4,), -2.0, dtype=torch.float64)
        """The largest ``h1``, ``h2``, ``-h1``, ``-h2`` of the same rays (-2: none seen)."""
        self.highest_up = -1.0
        self.open_rays = 0
        self.rays = 0

    def add(
        self,
        colours: Float[Tensor, "N 3"],
        open_share: Float[Tensor, "N 1"],
        up: Float[Tensor, "N 1"],
        level: Optional[Float[Tensor, "N 2"]] = None,
    ) -> None:
        """Count a batch: ``colours`` (linear RGB), ``open_share`` the geometry's transmittance past
        the last sample, ``up`` the ``sin`` of the rays' elevations, ``level`` their level components
        (``None``: all rays look one way round the horizon, and no change across it is read)."""
        is_open = is_open_water(open_share.detach()[..., 0])
        colour = colours.detach()[is_open].double().cpu()
        up_open = up.detach()[is_open].double().clamp(-1.0, 1.0).cpu()
        level_open = (
            torch.zeros(up_open.shape[0], 2, dtype=torch.float64)
            if level is None
            else level.detach()[is_open].double().clamp(-1.0, 1.0).cpu()
        )
        self.total += colour.sum(dim=0)
        self.total_up_colour += (up_open * colour).sum(dim=0)
        self.total_up += torch.stack([up_open.sum(), (up_open**2).sum()])
        above = up_open[:, 0] > 0
        features = torch.cat([torch.ones_like(up_open), up_open, level_open], dim=1)[above]
        self.above_gram += features.T @ features
        self.above_colour += features.T @ colour[above]
        if bool(above.any()):
            extent = torch.cat([level_open[above], -level_open[above]], dim=1).amax(dim=0)
            self.level_extent = torch.maximum(self.level_extent, extent)
        if up_open.numel():
            self.highest_up = max(self.highest_up, float(up_open.max()))
        self.open_rays += int(colour.shape[0])
        self.rays += int(is_open.numel())

    def _summed(self) -> Tensor:
        """The sums that add up over batches and processes, packed: 8 + 16 + 12 numbers."""
        return torch.cat([self.total, self.total_up_colour, self.total_up, self.above_gram.reshape(-1), self.above_colour.reshape(-1)])

    def _unpack_summed(self, packed: Tensor) -> None:
        self.total, self.total_up_colour, self.total_up = packed[:3], packed[3:6], packed[6:8]
        self.above_gram = packed[8:24].reshape(FEATURES, FEATURES).clone()
        self.above_colour = packed[24:36].reshape(FEATURES, 3).clone()

    def get_extra_state(self) -> Float[Tensor, "43"]:
        """The sums packed in one float64 tensor (every count below 2**53 is exact), so that code
        that treats a state dict's values as tensors keeps working: the 8 sums of all open rays, the
        highest ``up`` and the two counts, then the sums above the level (28) and their extent (4)."""
        counts = torch.tensor([self.highest_up, self.open_rays, self.rays], dtype=torch.float64)
        summed = self._summed()
        return torch.cat([summed[:8], counts, summed[8:], self.level_extent])

    def set_extra_state(self, state: Float[Tensor, "43"]) -> None:
        """The sums of :meth:`get_extra_state`. A checkpoint from before the sums above the level (11
        numbers) has none of those; one from before the level components (20) has the count, colour,
        ``up`` and ``up²`` sums above the level and no change round the horizon."""
        if torch.distributed.is_available() and torch.distributed.is_initialized() and torch.distributed.get_rank() != 0:
            return  # the checkpoint holds the first process's sums: the pooled mean counts them once
        packed = state.detach().double().cpu().clone()
        self.highest_up, self.open_rays, self.rays = float(packed[8]), int(packed[9]), int(packed[10])
        summed = torch.zeros(36, dtype=torch.float64)
        summed[:8] = packed[:8]
        self.level_extent = torch.full((4,), -2.0, dtype=torch.float64)
        if packed.numel() >= 43:
            summed[8:] = packed[11:39]
            self.level_extent = packed[39:43].clone()
        elif packed.numel() >= 20:  # count, colour (3), up colour (3), up, up^2
            above = packed[11:20]
            gram, colour = torch.zeros(FEATURES, FEATURES, dtype=torch.float64), torch.zeros(FEATURES, 3, dtype=torch.float64)
            gram[0, 0], gram[0, 1], gram[1, 0], gram[1, 1] = above[0], above[7], above[7], above[8]
            colour[0], colour[1] = above[1:4], above[4:7]
            summed[8:24], summed[24:36] = gram.reshape(-1), colour.reshape(-1)
        self._unpack_summed(summed)

    def pooled(self, device: torch.device | str = "cpu") -> "OpenWaterColour":
        """These sums over every process of a distributed run (``self`` where there is none), so that
        every process holds the same veil; ``device``: where the collective runs (the model's)."""
        if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
            return self
        counts = torch.tensor([self.open_rays, self.rays], dtype=torch.float64)
        packed = torch.cat([self._summed(), counts]).to(device)
        torch.distributed.all_reduce(packed)
        packed = packed.cpu()
        largest = torch.cat([torch.tensor([self.highest_up], dtype=torch.float64), self.level_extent]).to(device)
        torch.distributed.all_reduce(largest, op=torch.distributed.ReduceOp.MAX)
        largest = largest.cpu()
        pooled = OpenWaterColour()
        pooled.highest_up, pooled.level_extent = float(largest[0]), largest[1:].clone()
        pooled._unpack_summed(packed[:36])
        pooled.open_rays, pooled.rays = int(packed[36]), int(packed[37])
        return pooled

    def mean(self) -> Optional[Float[Tensor, "3"]]:
        """The open rays' mean colour, or ``None`` where under :data:`MIN_OPEN_FRACTION` of the rays were open."""
        if self.open_rays == 0 or self.open_rays < MIN_OPEN_FRACTION * self.rays:
            return None
        return self.total / self.open_rays

    def line_above_level(self) -> Optional[Tuple[float, Float[Tensor, "3"], Float[Tensor, "3"]]]:
        """``(mean up, mean colour, slope)`` of the open rays above the level plane (``up > 0``): the
        least-squares line ``colour = mean colour + slope (up − mean up)``, per channel. ``None`` where
        fewer than :data:`MIN_OPEN_FRACTION` of the open rays look up, or their ``up`` spreads by under
        1e-4 (standard deviation; the slope's denominator is its square)."""
        count = float(self.above_gram[0, 0])
        if count <= 0 or count < MIN_OPEN_FRACTION * self.open_rays:
            return None
        up_above = float(self.above_gram[0, 1]) / count
        spread = float(self.above_gram[1, 1]) / count - up_above**2
        if spread < 1e-8:
            return None
        colour_above = self.above_colour[0] / count
        return up_above, colour_above, (self.above_colour[1] / count - up_above * colour_above) / spread

    def across(self) -> Optional[Tuple[Float[Tensor, "2"], Float[Tensor, "2 3"], Float[Tensor, "2"], Float[Tensor, "2"]]]:
        """``(mean h, slope, lowest h, highest h)`` of the open water's colour round the horizon: the
        least-squares plane ``colour = a + s up + slope · h`` over the open rays above the level
        (those :meth:`line_above_level` reads, with their elevation as a covariate, so a rig that looks
        up more on one side does not read the rise as a change round the horizon), ``slope`` per unit of
        each level component ``h`` (rows) and channel; the mean and extent of their ``h``. ``None``
        where :meth:`line_above_level` is, or their ``h`` spreads by under 1e-4 (standard deviation)
        along some direction once ``up`` is accounted for."""
        if self.line_above_level() is None:
            return None
        count = float(self.above_gram[0, 0])
        mean = self.above_gram[0] / count
        covariance = self.above_gram[1:, 1:] / count - torch.outer(mean[1:], mean[1:])  # of (up, h1, h2)
        level_given_up = covariance[1:, 1:] - torch.outer(covariance[1:, 0], covariance[0, 1:]) / covariance[0, 0]
        if float(torch.linalg.eigvalsh(level_given_up).min()) < 1e-8:
            return None
        colour_covariance = self.above_colour[1:] / count - torch.outer(mean[1:], self.above_colour[0] / count)
        coefficients = torch.linalg.solve(covariance, colour_covariance)  # [3 (up, h1, h2), 3 channels]
        return mean[2:].clone(), coefficients[1:].clone(), -self.level_extent[2:].clone(), self.level_extent[:2].clone()

    def rise(self) -> Optional[Tuple[Float[Tensor, "3"], Float[Tensor, "3"], float]]:
        """``(start, slope, highest up)``, or ``None`` where :meth:`mean` is: the veil rises from ``start``
        (``sin(elevation)``, per channel) by ``slope`` (colour per unit of ``up``) up to the highest
        open ray's ``up``.

        The line is the least-squares fit of the colour over ``up`` of the open rays above the level
        plane, where at least :data:`MIN_OPEN_FRACTION` of the open rays are and their elevations spread;
        the veil rises from where that line passes the mean colour, between the mean elevation and the
        highest open ray. Below the level the first stage counts as open the far seabed its geometry
        has not formed yet: a line through those rays is 2–11× too flat (docs/history.md, 2026-11-29).
        Without rays above the level, the line of all the open rays from their mean elevation; no slope
        where their elevations spread by under 1e-4 in ``up``."""
        mean = self.mean()
        if mean is None:
            return None
        n = self.open_rays
        mean_up = float(self.total_up[0]) / n
        line = self.line_above_level()
        if line is not None:
            up_above, colour_above, slope = line
            rising = slope > 0
            crossing = up_above + (mean - colour_above) / torch.where(rising, slope, torch.ones_like(slope))
            start = torch.where(rising, crossing, torch.full_like(slope, mean_up))
            return start.clamp(mean_up, max(mean_up, self.highest_up)), slope, self.highest_up
        spread = float(self.total_up[1]) / n - mean_up**2
        start = torch.full((3,), mean_up, dtype=torch.float64)
        if spread < 1e-8:
            return start, torch.zeros(3, dtype=torch.float64), self.highest_up
        return start, (self.total_up_colour / n - mean_up * self.total / n) / spread, self.highest_up


DARK_QUANTILE = 0.01
"""Sea-thru's share of darkest pixels: each bound is this quantile of the per-observation bounds."""


def backscatter_density_bounds(
    ranges: Float[Tensor, "N"], colours: Float[Tensor, "N 3"], veil: Float[Tensor, "3"]
) -> Float[Tensor, "N 3"]:
    """Per observation and channel, the largest ``β_B`` (per world unit) that keeps the backscatter
    at or below the observed colour: ``-ln(1 - I / B∞) / z``, computed as ``-log1p(-I / B∞) / z``.
    ``inf`` where ``I >= B∞`` (any density keeps ``B∞ (1 - e^{-β_B z}) < B∞ <= I``), ``0`` where
    ``I <= 0``; ``ranges > 0``, ``veil >= 0`` (a zero veil bounds nothing: ``inf``)."""
    ratio = colours / veil.clamp_min(torch.finfo(colours.dtype).tiny)
    below = ratio < 1.0
    safe_ratio = torch.where(below, ratio.clamp_min(0.0), torch.zeros_like(ratio))  # log1p(-1) never taken
    bound = -torch.log1p(-safe_ratio) / ranges[:, None]
    return torch.where(below & (veil > 0), bound, torch.full_like(bound, float("inf")))


def backscatter_density_cap(
    ranges: Float[Tensor, "N"], colours: Float[Tensor, "N 3"], veil: Float[Tensor, "3"], quantile: float = DARK_QUANTILE
) -> Float[Tensor, "3"]:
    """The ``quantile`` of :func:`backscatter_density_bounds` per channel over the observations
    with finite positive range and finite colour (``inf`` where none, or where the quantile falls
    among the unbounded ones). Per world unit."""
    usable = usable_observations(ranges, colours)
    if not bool(usable.any()):
        return torch.full_like(veil, float("inf"))
    bounds = backscatter_density_bounds(ranges[usable], colours[usable], veil)
    return torch.quantile(bounds, quantile, dim=0, interpolation="lower")


def attenuation_bounds(
    ranges: Float[Tensor, "N"], colours: Float[Tensor, "N 3"], veil: Float[Tensor, "3"], beta_b: Float[Tensor, "3"]
) -> Float[Tensor, "N 3"]:
    """Per observation and channel, the largest ``β_D`` (per world unit) at which an object colour
    ``J <= 1`` still reaches the colour left above the backscatter: ``-ln(I - B∞ (1 - e^{-β_B z})) / z``.
    ``inf`` where the backscatter alone reaches ``I`` (any attenuation fits), ``0`` where what is
    left is 1 or more; ``ranges > 0``, ``beta_b`` per world unit."""
    direct = colours - veil * -torch.expm1(-beta_b * ranges[:, None])
    bounded = direct > 0
    safe = torch.where(bounded, direct.clamp(max=1.0), torch.ones_like(direct))  # log(0) never taken
    bound = -torch.log(safe) / ranges[:, None]
    return torch.where(bounded, bound, torch.full_like(bound, float("inf")))


def usable_observations(ranges: Float[Tensor, "N"], colours: Float[Tensor, "N 3"]) -> Float[Tensor, "N"]:
    """The observations with a finite positive range and a finite colour."""
    return torch.isfinite(ranges) & (ranges > 0) & torch.isfinite(colours).all(dim=-1)


def attenuation_cap(
    ranges: Float[Tensor, "N"],
    colours: Float[Tensor, "N 3"],
    veil: Float[Tensor, "3"],
    beta_b: Float[Tensor, "3"],
    quantile: float = DARK_QUANTILE,
) -> Float[Tensor, "3"]:
    """The ``quantile`` of :func:`attenuation_bounds` per channel over the usable observations
    (``inf`` where none). Per world unit."""
    usable = usable_observations(ranges, colours)
    if not bool(usable.any()):
        return torch.full_like(veil, float("inf"))
    bounds = attenuation_bounds(ranges[usable], colours[usable], veil, beta_b)
    return torch.quantile(bounds, quantile, dim=0, interpolation="lower")


def apply_density_caps(model: Any, step: int, optimizers: Any = None) -> None:
    """Callback at the end of the first stage: set the veiling light to the open water's mean colour
    and its rise looking up (:class:`OpenWaterColour`, where it saw enough open rays, pooled over the
    processes of a distributed run), then lower the scene medium's backscatter densities to
    :func:`backscatter_density_cap` of the dataparser's SfM observations under the veiling light
    learned so far, then its attenuations to :func:`attenuation_cap` under that backscatter; a
    density already below its cap stays. ``optimizers``: the trainer's, whose
    ``medium_density`` Adam state is cleared where a density moved."""
    config = model.config
    if not TrainingPhases(config, step).ends(config.medium_first_steps) or config.medium_scope != "scene":
        return
    if config.research.medium_oracle is not None or model.medium_model == "none":
        return  # an oracle is the medium; clear air renders none
    read = model.open_water_colour.pooled(model.device)  # every process of a distributed run alike
    open_water, rise = read.mean(), read.rise()
    if open_water is not None and rise is not None:
        open_water = open_water.clamp(1e-4, 1 - 1e-4)
        with torch.no_grad():
            learned = torch.sigmoid(model.medium_field.rgb_logit.double())
            model.medium_field.rgb_logit.copy_(torch.logit(open_water).to(model.medium_field.rgb_logit))
        gain = rise[1].clamp_min(0.0) / open_water  # brighter looking up only: light falls from above
        model.medium_field.set_veil_rise(rise[0], gain.float(), rise[2])  # not beyond the open water seen
        across = read.across()
        if across is not None:
            model.medium_field.set_veil_across(across[0], across[1] / open_water, across[2], across[3])
        show = lambda values: ", ".join(f"{float(v):.3g}" for v in values)  # noqa: E731
        change = "" if across is None else f", changing round the horizon by {show((across[1] / open_water).reshape(-1))} per unit"
        CONSOLE.print(
            f"[bold]seathru step {step}: B_inf {show(learned)} -> {show(open_water)}, the colour of "
            f"{read.open_rays} open rays, rising by {show(gain)} per unit of sin(elevation) above {show(rise[0])}{change}; held from here"
        )
    table = (model.kwargs.get("metadata") or {}).get(SFM_OBSERVATIONS_KEY)
    if table is None or table.num_observations == 0:
        return
    medium = model.medium_field
    with torch.no_grad():
        densities = torch.nn.functional.softplus(medium.density_raw.double()) * model.world_scale  # per world unit
        veil = torch.sigmoid(medium.rgb_logit.double())
    seen = torch.isfinite(torch.from_numpy(table.ranges))
    ranges, colours = torch.from_numpy(table.ranges)[seen], torch.from_numpy(table.colours)[seen]
    beta_b = torch.minimum(densities[3:], backscatter_density_cap(ranges, colours, veil).clamp_min(DENSITY_FLOOR))
    beta_d = torch.minimum(densities[:3], attenuation_cap(ranges, colours, veil, beta_b).clamp_min(DENSITY_FLOOR))
    capped = torch.cat([beta_d, beta_b])
    if bool((capped >= densities).all()):
        return
    medium.set_densities(capped / model.world_scale)
    if optimizers is not None and "medium_density" in optimizers.optimizers:
        optimizers.optimizers["medium_density"].state.clear()
    show = lambda values: ", ".join(f"{float(v):.3g}" for v in values)  # noqa: E731
    CONSOLE.print(
        f"[bold]seathru step {step}: densities bounded by the darkest and brightest 1% of {table.num_observations} SfM "
        f"observations under B_inf {show(veil)}: beta_D {show(densities[:3])} -> {show(beta_d)}, "
        f"beta_B {show(densities[3:])} -> {show(beta_b)} /m"
    )
