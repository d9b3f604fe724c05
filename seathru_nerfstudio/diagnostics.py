"""Is the decomposition working? Numbers a user can read while training.

A broken decomposition looks fine in the in-medium image: the object field can fill the
open water with a wall of water colour, or the medium can become a veil in front of the
lens. These numbers show it at a glance (TensorBoard's *Train Metrics Dict* and one log
line every ``diagnostics_every`` steps):

* ``accumulation``: mean object opacity of the batch's rays;
* ``accumulation_open_water``: the same on rays whose true range is infinite (synthetic
  scenes only): it should be 0;
* ``depth_error``: median of ``|depth - true range| / true range`` on rays that hit an object
  (synthetic scenes only): a surface at the wrong distance means a wrong medium or a wrong
  clean colour, even when the in-medium image fits;
* ``medium_beta_D``, ``medium_beta_B`` (per world unit, i.e. 1/m for metric captures) and
  ``medium_B_inf``, per channel, mean over the batch's rays;
* ``backscatter_share``: the share of the in-medium image that is backscatter;
* ``direct_share_r``, ``_g``, ``_b``: per channel, the share of the in-medium image that is the
  object's attenuated colour. One channel near 0 while the others are not is a dead colour
  channel: the object colour's sigmoid saturated at black and the backscatter explains that
  channel alone, which shows as a pink or purple ``clean`` image (measured on the water and fog
  demos on 2026-11-25: docs/history.md, *A dead colour channel*); the log line then names the channel;
* ``medium_model`` (added by the model): the medium model in use, as its index in
  :data:`~seathru_nerfstudio.medium_field.MEDIUM_MODELS` (-1: ``auto`` before its decision).
"""

from __future__ import annotations

from typing import Dict, Mapping, Optional

import torch
from torch import Tensor

from seathru_nerfstudio.medium_field import MEDIUM_MODELS

CHANNELS = ("r", "g", "b")


@torch.no_grad()
def decomposition(outputs: Mapping[str, Tensor], gt_depth: Optional[Tensor], world_scale: float) -> Dict[str, Tensor]:
    """Diagnostics of one batch of rays (``outputs`` of ``SeathruModel.get_outputs``).

    ``gt_depth``: true range per ray, ``inf`` for open water (or ``None``); ``world_scale``:
    scene units per world unit, so that ``sigma [1/unit] * world_scale = beta [1/world unit]``.
    """
    values: Dict[str, Tensor] = {"accumulation": outputs["accumulation"].float().mean()}
    if gt_depth is not None:
        open_water = ~torch.isfinite(gt_depth.to(outputs["accumulation"].device))
        if open_water.any():
            values["accumulation_open_water"] = outputs["accumulation"].float()[open_water].mean()
        truth = gt_depth.to(outputs["accumulation"].device).float()
        hit = torch.isfinite(truth) & (truth > 0)
        if "depth" in outputs and hit.any():
            error = (outputs["depth"].float()[hit] - truth[hit]).abs() / truth[hit]
            values["depth_error"] = error.median()
    media = {
        "beta_D": outputs["medium_attenuation"].float() * world_scale,
        "beta_B": outputs["medium_backscatter"].float() * world_scale,
        "B_inf": outputs["medium_rgb"].float(),
    }
    for name, value in media.items():
        mean = value.reshape(-1, 3).mean(dim=0)
        for channel, v in zip(CHANNELS, mean):
            values[f"medium_{name}_{channel}"] = v
    rgb = outputs["rgb"].float().sum()
    values["backscatter_share"] = outputs["backscatter"].float().sum() / torch.clamp(rgb, min=1e-12)
    if "direct" in outputs:
        direct = outputs["direct"].float().reshape(-1, 3).sum(dim=0)
        per_channel = outputs["rgb"].float().reshape(-1, 3).sum(dim=0)
        for channel, d, total in zip(CHANNELS, direct, per_channel):
            values[f"direct_share_{channel}"] = d / torch.clamp(total, min=1e-12)
    return values


DEAD_CHANNEL_SHARE = 0.01
"""A channel whose direct share is below this, while another channel's is at least
:data:`LIVE_CHANNEL_SHARE`, is reported as dead in the log line."""
LIVE_CHANNEL_SHARE = 0.05


def dead_channels(values: Mapping[str, Tensor]) -> str:
    """The channels (``"g"``, ``"gb"``, ...) whose object colour looks dead; ``""`` if none or
    if the direct shares are not in ``values``."""
    if not all(f"direct_share_{c}" in values for c in CHANNELS):
        return ""
    shares = {c: float(values[f"direct_share_{c}"]) for c in CHANNELS}
    if max(shares.values()) < LIVE_CHANNEL_SHARE:
        return ""
    return "".join(c for c in CHANNELS if shares[c] < DEAD_CHANNEL_SHARE)


def format_line(values: Mapping[str, Tensor]) -> str:
    """One readable line: ``acc 0.42 (open water 0.03)  beta_D 1.3 1.2 0.9 /unit ...``."""

    def rgb(name: str) -> str:
        return " ".join(f"{float(values[f'medium_{name}_{c}']):.3g}" for c in CHANNELS)

    acc = f"acc {float(values['accumulation']):.2f}"
    if "accumulation_open_water" in values:
        acc += f" (open water {float(values['accumulation_open_water']):.2f})"
    if "depth_error" in values:
        acc += f"  depth error {float(values['depth_error']):.2f}"
    model = ""
    if "medium_model" in values:
        code = int(values["medium_model"])
        model = f"medium {MEDIUM_MODELS[code] if 0 <= code < len(MEDIUM_MODELS) else 'auto (deciding)'}  "
    line = (
        f"{model}{acc}  beta_D {rgb('beta_D')}  beta_B {rgb('beta_B')} /world unit  "
        f"B_inf {rgb('B_inf')}  backscatter share {float(values['backscatter_share']):.2f}"
    )
    if all(f"direct_share_{c}" in values for c in CHANNELS):
        line += "  direct share " + " ".join(f"{float(values[f'direct_share_{c}']):.2f}" for c in CHANNELS)
        dead = dead_channels(values)
        if dead:
            line += f"  DEAD COLOUR CHANNEL {' '.join(dead)} (the clean image lacks it)"
    return line
