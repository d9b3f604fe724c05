"""The veiling light read from the open water: the mean colour the camera sees where a ray meets
nothing, set at ``medium_fit_step`` and held from then on, as the fitted densities are.

``B∞`` is what a ray that passes no matter shows (:func:`~seathru_nerfstudio.rendering.render_seathru`:
an empty ray renders exactly ``c_med``). From the end of the first stage to the fit, every training
batch adds its observed colours ``I_r`` weighted by the share of each ray the object field leaves
open, ``T_r = e^{-τ_N}``; the estimate is

    B̂∞ = Σ_t d^{t_fit - t} Σ_r T_r I_r  /  Σ_t d^{t_fit - t} Σ_r T_r,      d = 1 - 1 / window,

a running mean over about the last ``window`` steps, so that it reads the geometry learned by then.

Why not the veil the renderer learned: real open water is not uniform (light from above makes it
brighter towards the surface), and the object field fills the darker part of it with matter, whose
colour takes that part of the open water. The veil learned by gradient then only has to match the
rays left empty, the brightest. On the path-traced scenes at step 499 (seed 42), with
``T > 0.95`` rays all truly open:

================  ===========================  ===========================  ============================
scene             learned veil                 B̂∞ (this estimate)           mean of the truly open rays
================  ===========================  ===========================  ============================
fog               0.256, 0.300, 0.395          0.229, 0.260, 0.331          0.243, 0.280, 0.365
coastal           0.052, 0.270, 0.568          0.052, 0.240, 0.466          0.050, 0.234, 0.464
================  ===========================  ===========================  ============================

The scenes' best-fitting ``B∞`` (true range and ``J``) is 0.220, 0.249, 0.316 (fog) and 0.041, 0.204,
0.437 (coastal): the open water's mean is closer to it than the veil learned (docs/history.md,
2026-11-28, the open-water veil).

A scene without open water (a camera looking down at the bed) has nothing to read: where fewer
than ``min_open_share`` of the rays are more than half open, the learned veil stays.

Colours linear, as the training images; all sums in float64, as buffers (checkpointed, so a
resumed run continues the same estimate); under DDP the ranks' sums are added before the estimate.
"""

from __future__ import annotations

from typing import Any, Optional

import torch
from jaxtyping import Float
from torch import Tensor, nn

from nerfstudio.utils.rich_utils import CONSOLE


class OpenWaterVeil(nn.Module):
    """Running, open-share-weighted mean of the observed colour (see the module docstring)."""

    def __init__(self, window: float = 100.0, min_open_share: float = 0.01) -> None:
        """``window``: steps the running mean reaches back (``d = 1 - 1/window``, > 1);
        ``min_open_share``: least share of rays more than half open for an estimate, in (0, 1)."""
        super().__init__()
        if not window > 1.0:
            raise ValueError(f"the open-water window must be more than one step, got {window}")
        self.decay = 1.0 - 1.0 / window
        self.min_open_share = min_open_share
        self.register_buffer("colour_sum", torch.zeros(3, dtype=torch.float64))
        """Σ d^age T_r I_r, linear RGB."""
        self.register_buffer("open_sum", torch.zeros((), dtype=torch.float64))
        """Σ d^age T_r."""
        self.register_buffer("half_open_count", torch.zeros((), dtype=torch.float64))
        """Σ d^age [T_r > 1/2]."""
        self.register_buffer("ray_count", torch.zeros((), dtype=torch.float64))
        """Σ d^age 1."""

    @torch.no_grad()
    def update(self, open_share: Float[Tensor, "*batch 1"], colours: Float[Tensor, "*batch 3"]) -> None:
        """Age the sums by one step and add one batch: ``open_share`` ``T_r`` in [0, 1] (clamped),
        ``colours`` the observed linear RGB of the same rays. Non-finite colours count as absent."""
        share = open_share.detach().reshape(-1).to(self.colour_sum).clamp(0.0, 1.0)
        rgb = colours.detach().reshape(-1, 3).to(self.colour_sum)
        finite = torch.isfinite(rgb).all(dim=-1)
        share = torch.where(finite, share, torch.zeros_like(share))
        rgb = torch.where(finite[:, None], rgb, torch.zeros_like(rgb))
        for buffer in (self.colour_sum, self.open_sum, self.half_open_count, self.ray_count):
            buffer.mul_(self.decay)
        self.colour_sum.add_((share[:, None] * rgb).sum(dim=0))
        self.open_sum.add_(share.sum())
        self.half_open_count.add_((share > 0.5).to(share).sum())
        self.ray_count.add_(finite.to(share).sum())

    def _summed(self) -> list[Tensor]:
        sums = [self.colour_sum.clone(), self.open_sum.clone(), self.half_open_count.clone(), self.ray_count.clone()]
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            for value in sums:
                torch.distributed.all_reduce(value)
        return sums

    def estimate(self) -> Optional[Float[Tensor, "3"]]:
        """``B̂∞`` (linear RGB, float64), or ``None`` where the open water was not seen: no ray, or
        fewer than ``min_open_share`` of them more than half open."""
        colour_sum, open_sum, half_open, rays = self._summed()
        if not (rays > 0 and open_sum > 0 and half_open >= self.min_open_share * rays):
            return None
        return colour_sum / open_sum


def hold_open_water_veil(model: Any, step: int, optimizers: Any = None) -> None:
    """At ``medium_fit_step`` (before the densities are fitted under it): set a scene medium's veil
    to the open water's colour (:class:`OpenWaterVeil`) and hold it (``model.veil_held``).
    ``optimizers``: the trainer's, whose Adam state of the veil is cleared."""
    medium = model.medium_field
    estimate = model.open_water_veil.estimate()
    show = lambda values: ", ".join(f"{float(v):.3g}" for v in values)  # noqa: E731
    if estimate is None:
        CONSOLE.print(
            f"[bold yellow]seathru step {step}: no open water seen (fewer than "
            f"{model.open_water_veil.min_open_share:.0%} of the rays half open): the veiling light learned stays"
        )
        return
    tiny = torch.finfo(medium.rgb_logit.dtype).eps
    learned = torch.sigmoid(medium.rgb_logit.detach().double())
    with torch.no_grad():
        medium.rgb_logit.copy_(torch.logit(estimate.clamp(tiny, 1.0 - tiny)).to(medium.rgb_logit))
    if optimizers is not None and "medium" in optimizers.optimizers:
        optimizers.optimizers["medium"].state.pop(medium.rgb_logit, None)
    model.veil_held.fill_(True)
    CONSOLE.print(f"[bold]seathru step {step}: B_inf {show(learned)} -> {show(estimate)}, the open water's colour; held")
