"""Image and depth metrics, with LPIPS only when its weights are already on disk."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Callable, Optional

import torch
from jaxtyping import Float
from torch import Tensor
from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

_LPIPS = LearnedPerceptualImagePatchSimilarity  # bound now: models patch the module attribute

ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"
"""torchvision's AlexNet checkpoint that torchmetrics' LPIPS loads (from the torch hub cache)."""

_warned = False


def lpips_weights_path() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_WEIGHTS


def make_lpips(**kwargs) -> Optional[Callable]:
    """torchmetrics' LPIPS if AlexNet's weights are on disk; otherwise ``None`` and one warning.

    Never downloads: offline, nerfstudio's own models crash here before step 0.
    """
    global _warned
    path = lpips_weights_path()
    if path.is_file():
        return _LPIPS(**kwargs)
    if not _warned:
        warnings.warn(
            f"LPIPS disabled: AlexNet weights not found at {path} and nothing will be downloaded. "
            "Copy the file there to enable LPIPS.",
            stacklevel=2,
        )
        _warned = True
    return None


def psnr(pred: Float[Tensor, "*batch 3"], target: Float[Tensor, "*batch 3"]) -> float:
    """PSNR in dB for images with data range 1 (linear or sRGB, as given)."""
    mse = torch.mean((pred.float() - target.float()) ** 2)
    return float(-10.0 * torch.log10(mse.clamp_min(1e-20)))


def depth_abs_rel(
    pred: Float[Tensor, "*batch 1"], target: Float[Tensor, "*batch 1"], mask: Optional[Tensor] = None
) -> float:
    """Mean ``|pred - target| / target`` over finite, positive ground truth (and ``mask``)."""
    valid = torch.isfinite(target) & (target > 0)
    if mask is not None:
        valid = valid & mask
    if not bool(valid.any()):
        return float("nan")
    p, t = pred[valid].float(), target[valid].float()
    return float(torch.mean(torch.abs(p - t) / t))


def far_third_mask(target: Float[Tensor, "*batch 1"]) -> Tensor:
    """Pixels whose finite ground-truth depth lies in the farthest third (by quantile)."""
    valid = torch.isfinite(target) & (target > 0)
    if not bool(valid.any()):
        return valid
    threshold = torch.quantile(target[valid].float(), 2.0 / 3.0)
    return valid & (target >= threshold)
