"""Diagnostic oracles: the true medium of a synthetic scene put in place of a learned one, to
split a run's error between the medium and the rest (``--pipeline.model.research.medium-oracle``,
``research.medium-fit-oracle``). Units: densities in 1/world unit in the file, 1/scene unit in
the model (divided by the dataparser scale)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Dict, List, Tuple

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from seathru_nerfstudio.medium_field import FixedMedium, SceneMedium

TrueMedium = Dict[str, List[float]]


def read_true_medium(path: Path) -> TrueMedium:
    """``beta_D``, ``beta_B`` (1/world unit) and ``B_inf`` of a ``medium.json`` as ``seathru-synth``
    writes it, three finite numbers each; a ``ValueError`` naming the file if it is not one."""
    try:
        truth = json.loads(Path(path).read_text())
        values = {key: [float(v) for v in truth[key]] for key in ("beta_D", "beta_B", "B_inf")}
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise ValueError(f"{path} is not a medium.json with beta_D, beta_B and B_inf: {error!r}") from error
    if any(len(v) != 3 or not all(math.isfinite(x) for x in v) for v in values.values()):
        raise ValueError(f"{path}: beta_D, beta_B and B_inf must be three finite numbers each")
    return values


def oracle_medium(truth: TrueMedium, world_scale: float, learns: bool) -> torch.nn.Module:
    """The true medium as the model's medium: held fixed, or (``learns``) a scene medium that starts
    there. ``world_scale``: scene units per world unit."""
    densities = [b / world_scale for b in [*truth["beta_D"], *truth["beta_B"]]]
    if learns:
        return SceneMedium(init_density=densities, init_rgb=truth["B_inf"])
    return FixedMedium(rgb=truth["B_inf"], sigma_attn=densities[:3], sigma_bs=densities[3:])


def replace_with_truth(
    truth: TrueMedium,
    parts: str,
    beta_d: Float[Tensor, "3"],
    beta_b: Float[Tensor, "3"],
    replaced: Bool[Tensor, "3"],
) -> Tuple[Float[Tensor, "3"], Float[Tensor, "3"], Bool[Tensor, "6"]]:
    """The fit's densities (1/world unit) with the true ones in place of ``parts`` (``both``,
    ``attenuation``: ``β_D``, ``backscatter``: ``β_B``), and which of the six are now set."""
    replaced_d = replaced_b = replaced
    if parts != "backscatter":
        beta_d, replaced_d = torch.tensor(truth["beta_D"], dtype=beta_d.dtype), torch.ones_like(replaced)
    if parts != "attenuation":
        beta_b, replaced_b = torch.tensor(truth["beta_B"], dtype=beta_b.dtype), torch.ones_like(replaced)
    return beta_d, beta_b, torch.cat([replaced_d, replaced_b])
