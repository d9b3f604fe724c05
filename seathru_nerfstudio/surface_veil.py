"""The veil in front of the surfaces, read from the surfaces whose own light the water has put out.

SeaThru's formation model has one veil ``B∞``: the colour of open water and the colour every surface fades
to with range. Path-traced water does not keep them equal. On coastal layout 7 the open water's mean is
0.0474, 0.225, 0.445 (linear RGB), while the surfaces' best fit is 0.0398, 0.209, 0.431 and the surfaces
whose own light the water has put out (``β_D z >= 3``: under 5% of what leaves them reaches the camera)
show a median of 0.0397 in red and 0.192 in green (true range and ``β_D``; blue has no such surfaces).
Held at the open water's colour, the veil in front of the surfaces is 19% too bright in red: the medium
fit's ``β_B`` falls with it (red −51%: ``medium_fit.veil_sensitivity``), and surfaces past the SfM far bound
come too near, where that veil's backscatter matches their colour (docs/history.md, 2026-12-07).

So the scene medium renders two veils (:func:`~seathru_nerfstudio.rendering.render_seathru`'s
``surface_veil``): ``r B∞`` in front of every surface, with ``r <= 1`` per channel, and ``B∞`` in open water,
whose excess ``(1 − r) B∞`` reaches a ray only past all matter. ``r`` is read here, from the training rays
that end on a surface (accumulation >= :data:`SURFACE_ACCUMULATION`) in the steps before the medium fit: the
median of their colour over the veil they are rendered with, among those whose optical depth under the
fitted attenuation is at least ``min_optical_depth``. A channel is read only where that depth lies within the
SfM far bound, so that the SfM shows surfaces that deep exist: past the bound the object field builds a wall of
whatever it meets. On coastal layout 3 rendered again, seed 42, blue's depth of 3 attenuation lengths (21.8 m)
lay past the bound (17.3 m), and the rays placed there were open water and surfaces truly 13 m away, whose blue
still carried a fifth of their own light: blue read 0.775 where its best fit is 0.86 (``β_B`` +49%). Reading
only within the bound lost the far surfaces that a channel whose depth lies within it reads well (coastal 7,
seed 42: red's deep rays 5.1% of the surface rays, 0.46% within the bound; docs/history.md, 2026-12-07).
Rays are binned by range and by that ratio, so the attenuation can be chosen after they are counted. Where
fewer than :data:`MIN_SURFACE_SHARE` of the surface rays are that deep, or the median is at or above 1, the
channel keeps ``r = 1`` (one veil, as SeaThru's).
On scenes drawn with the formation model a deep surface's colour is at or above its veil where ``β_B >= β_D``; where
``β_B < β_D`` it can fall short by up to ``e^{-β_B z}`` (water demo: green's deep pixels are 0.93 of the veil at the true
range, 0.2% of the pixels, but 0.03% of the surface rays the run renders that deep by step 500, under the floor), so
there ``r`` stays 1 only while such surfaces are few.
"""

from __future__ import annotations

from typing import Any, Optional

import torch
from jaxtyping import Float
from torch import Tensor

from nerfstudio.utils.rich_utils import CONSOLE

SURFACE_ACCUMULATION = 0.95
"""A training ray counts as ending on a surface where the object field's accumulation reaches this."""
MIN_SURFACE_SHARE = 0.001
"""A channel's ratio is read only where at least this share of the surface rays is deep enough (0.1%: 60–120 of
the 60,000–120,000 surface rays a 1500-step lite run counts; the water demo's unsaturated green, 0.03%, stays under it)."""
RANGE_BINS = 120
"""Bins of ``log10(range)`` over :data:`LOG_RANGE_SPAN` (12% wide each)."""
LOG_RANGE_SPAN = (-3.0, 3.0)
"""``log10`` of the shortest and longest range binned, in scene units; ranges outside fall in the end bins."""
RATIO_BINS = 200
"""Bins of colour / veil over ``[0, RATIO_TOP)`` (0.01 wide); ratios above fall in the last bin."""
RATIO_TOP = 2.0


def deep_bins(attenuation: float, min_optical_depth: float, max_range: Optional[float] = None) -> Float[Tensor, "R"]:
    """The range bins whose nearest range (scene units) times ``attenuation`` (per scene unit) is at least
    ``min_optical_depth``; none where that optical depth is first reached past ``max_range`` (scene units)."""
    if max_range is not None and not attenuation * max_range >= min_optical_depth:  # NaN reads nothing too
        return torch.zeros(RANGE_BINS, dtype=torch.bool)
    low, high = LOG_RANGE_SPAN
    nearest = torch.pow(10.0, low + (high - low) * torch.arange(RANGE_BINS, dtype=torch.float64) / RANGE_BINS)
    return attenuation * nearest >= min_optical_depth


class SurfaceVeil(torch.nn.Module):
    """The histogram of the surface rays' colour over their veil, per range bin and channel (module
    docstring). The counts are the module's extra state, as :class:`~seathru_nerfstudio.medium_start.OpenWaterColour`'s
    sums are: a checkpoint holds them, DDP does not overwrite them, and :meth:`pooled` adds them over processes."""

    def __init__(self) -> None:
        super().__init__()
        self.counts = torch.zeros(RANGE_BINS, 3, RATIO_BINS, dtype=torch.float64)

    def add(
        self,
        colours: Float[Tensor, "N 3"],
        veil: Float[Tensor, "N 3"],
        ranges: Float[Tensor, "N 1"],
        accumulation: Float[Tensor, "N 1"],
    ) -> None:
        """Count a batch: ``colours`` the observed pixels and ``veil`` the veil each ray is rendered with
        (linear), ``ranges`` the rendered range (scene units), ``accumulation`` the object field's."""
        with torch.no_grad():
            colours, veil = colours.detach().double().cpu(), veil.detach().double().cpu()
            ranges, accumulation = ranges.detach().double().cpu().reshape(-1), accumulation.detach().double().cpu().reshape(-1)
            keep = (accumulation >= SURFACE_ACCUMULATION) & torch.isfinite(ranges) & (ranges > 0)
            keep &= torch.isfinite(colours).all(dim=-1) & (veil > 0).all(dim=-1)
            if not bool(keep.any()):
                return
            low, high = LOG_RANGE_SPAN
            log_range = torch.log10(ranges[keep])
            range_bin = ((log_range - low) / (high - low) * RANGE_BINS).floor().clamp(0, RANGE_BINS - 1).long()
            ratio = colours[keep] / veil[keep]
            ratio_bin = (ratio / RATIO_TOP * RATIO_BINS).floor().clamp(0, RATIO_BINS - 1).long()  # [n, 3]
            channel = torch.arange(3).expand_as(ratio_bin)
            flat = (range_bin[:, None] * 3 + channel) * RATIO_BINS + ratio_bin
            self.counts += torch.bincount(flat.reshape(-1), minlength=self.counts.numel()).double().view_as(self.counts)

    @property
    def surface_rays(self) -> int:
        """How many surface rays were counted."""
        return int(self.counts[:, 0, :].sum())

    def ratio(
        self, attenuation: Float[Tensor, "3"], min_optical_depth: float, max_range: Optional[float] = None
    ) -> Float[Tensor, "3"]:
        """``r`` per channel (module docstring): the median colour / veil over the bins whose nearest range
        times ``attenuation`` (per scene unit) is at least ``min_optical_depth``, at most 1; 1 where under
        :data:`MIN_SURFACE_SHARE` of the surface rays are in those bins, or where that optical depth is first
        reached past ``max_range`` (scene units: the SfM far bound)."""
        total = float(self.counts[:, 0, :].sum())
        out = torch.ones(3, dtype=torch.float64)
        for c in range(3):
            deep = deep_bins(float(attenuation[c]), min_optical_depth, max_range)
            histogram = self.counts[deep, c, :].sum(dim=0)
            count = float(histogram.sum())
            if total <= 0 or count < MIN_SURFACE_SHARE * total:
                continue
            median_bin = int(torch.searchsorted(torch.cumsum(histogram, 0), torch.tensor(count / 2, dtype=torch.float64)))
            out[c] = min(1.0, (median_bin + 0.5) * RATIO_TOP / RATIO_BINS)
        return out

    def deep_share(
        self, attenuation: Float[Tensor, "3"], min_optical_depth: float, max_range: Optional[float] = None
    ) -> Float[Tensor, "3"]:
        """The share of the surface rays, per channel, that :meth:`ratio` reads (0 where none were counted)."""
        per_bin = self.counts[:, 0, :].sum(dim=-1)
        total = float(per_bin.sum())
        if total <= 0:
            return torch.zeros(3, dtype=torch.float64)
        return torch.stack(
            [per_bin[deep_bins(float(attenuation[c]), min_optical_depth, max_range)].sum() / total for c in range(3)]
        )

    def get_extra_state(self) -> Float[Tensor, "N"]:
        return self.counts.reshape(-1).clone()

    def set_extra_state(self, state: Optional[Tensor]) -> None:
        """The counts of :meth:`get_extra_state`; only the first process of a distributed run takes them."""
        if torch.distributed.is_available() and torch.distributed.is_initialized() and torch.distributed.get_rank() != 0:
            return
        if state is None or state.numel() != self.counts.numel():
            return
        self.counts = state.detach().double().cpu().reshape(self.counts.shape).clone()

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):  # noqa: ANN001
        """A checkpoint from before the surfaces' veil has no counts: none are loaded, none reported missing."""
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs)
        if prefix + "_extra_state" in missing_keys:
            missing_keys.remove(prefix + "_extra_state")

    def pooled(self, device: torch.device | str = "cpu") -> "SurfaceVeil":
        """These counts over every process of a distributed run (``self`` where there is none)."""
        if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
            return self
        counts = self.counts.reshape(-1).to(device)
        torch.distributed.all_reduce(counts)
        pooled = SurfaceVeil()
        pooled.counts = counts.cpu().reshape(self.counts.shape)
        return pooled


def read_surface_veil(model: Any, attenuation: Float[Tensor, "3"], step: int) -> Float[Tensor, "3"] | None:
    """The veil in front of the surfaces over the open water's, per channel, read from the surface rays
    counted before the fit (:class:`~seathru_nerfstudio.surface_veil.SurfaceVeil`) at the optical depth
    ``research.surface_veil_optical_depth`` under ``attenuation`` (1/world unit); ``None`` where it is 1 in
    every channel, the option is off, or the medium is not the scene medium."""
    min_optical_depth = model.config.research.surface_veil_optical_depth
    if min_optical_depth is None or not hasattr(model.medium_field, "surface_veil"):
        return None
    reader = model.surface_veil_reader.pooled(model.device)
    per_scene_unit = attenuation.double().cpu() / model.world_scale
    far = None if getattr(model, "far_range", None) is None else float(model.far_range) * model.world_scale
    share = reader.ratio(per_scene_unit, min_optical_depth, far)
    deep = reader.deep_share(per_scene_unit, min_optical_depth, far)
    show = lambda values: ", ".join(f"{float(v):.3g}" for v in values)  # noqa: E731
    within = "" if far is None else (
        f", a channel only where that depth is within the SfM far bound ({model.far_range:.3g} world units)"
    )
    CONSOLE.print(
        f"[bold]seathru step {step}: the veil in front of the surfaces is {show(share)} of the open water's[/] "
        f"(median over the {show(deep)} of {reader.surface_rays} surface rays at optical depth >= {min_optical_depth:g}"
        f"{within}; 1 where under {MIN_SURFACE_SHARE:.1%} are)"
    )
    return share if bool((share < 1).any()) else None
