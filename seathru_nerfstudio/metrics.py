"""Evaluation metrics, written once: ``SeathruModel.get_image_metrics_and_images`` (``ns-eval``,
the evaluations while training) and ``seathru-bench`` (``bench/scoring.py``) both score a view
with :func:`view_metrics`. LPIPS only when its weights are already on disk.
"""

from __future__ import annotations

import importlib
import math
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Dict, Iterator, Mapping, Optional

import torch
from jaxtyping import Float
from torch import Tensor
from torchmetrics.functional import structural_similarity_index_measure
from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

from seathru_nerfstudio.colour import linear_to_srgb

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
        return LearnedPerceptualImagePatchSimilarity(**kwargs)
    if not _warned:
        warnings.warn(
            f"LPIPS disabled: AlexNet weights not found at {path} and nothing will be downloaded. "
            "Copy the file there to enable LPIPS.",
            stacklevel=2,
        )
        _warned = True
    return None


@contextmanager
def offline_lpips() -> Iterator[None]:
    """Build nerfstudio models inside this block: their LPIPS comes from :func:`make_lpips`.

    nerfacto's ``populate_modules`` looks up ``LearnedPerceptualImagePatchSimilarity`` in
    ``torchmetrics.image.lpip`` and constructs it unconditionally, which downloads AlexNet (and
    crashes offline). It has no option to skip that, so for the duration of the block, and only
    then, that one name is :func:`make_lpips`; it is restored on exit, also on error. Used around
    model construction by ``SeathruModel`` and by the benchmark (for nerfacto).
    """
    module = importlib.import_module("torchmetrics.image.lpip")
    original = module.LearnedPerceptualImagePatchSimilarity
    module.LearnedPerceptualImagePatchSimilarity = make_lpips
    try:
        yield
    finally:
        module.LearnedPerceptualImagePatchSimilarity = original


def nchw(image: Float[Tensor, "H W C"]) -> Float[Tensor, "1 C H W"]:
    """An ``[H, W, C]`` image as the ``[1, C, H, W]`` batch torchmetrics takes."""
    return torch.moveaxis(image.float(), -1, 0)[None]


def ssim(pred: Float[Tensor, "H W 3"], target: Float[Tensor, "H W 3"]) -> float:
    """SSIM of two images with data range 1 (torchmetrics, as nerfacto)."""
    return float(structural_similarity_index_measure(nchw(pred), nchw(target), data_range=1.0))


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


def near_third_mask(target: Float[Tensor, "*batch 1"]) -> Tensor:
    """Object pixels (finite ground-truth range) in the nearest third by rank: of the ``n`` object
    pixels, the ``ceil(n / 3)`` with the smallest range (ties broken by pixel order), so the mask
    holds exactly that many; open water (``inf``) never. Nearest, because there the clean colour
    is least hidden by the water, so its error shows the decomposition rather than the noise."""
    valid = torch.isfinite(target)
    mask = torch.zeros_like(valid)
    index = torch.nonzero(valid.reshape(-1)).squeeze(1)
    if index.numel() == 0:
        return mask
    order = torch.argsort(target.reshape(-1)[index].float(), stable=True)
    mask.view(-1)[index[order[: math.ceil(index.numel() / 3)]]] = True
    return mask


def clean_psnrs(
    clean: Float[Tensor, "H W 3"], gt_clean: Float[Tensor, "H W 3"], gt_depth: Float[Tensor, "H W 1"]
) -> Dict[str, float]:
    """J (clean image) PSNR, the estimate clipped to [0, 1] as every image is scored:
    ``clean_psnr_objects`` over the object pixels (finite true range) and
    ``clean_psnr_near_third`` over the nearest third of them (:func:`near_third_mask`);
    ``nan`` where a view has no object pixel. Any range unit (the mask is by rank)."""
    clean = clean[..., :3].float().clamp(0.0, 1.0)
    gt_clean = gt_clean[..., :3].float()
    result = {}
    for key, mask in (("clean_psnr_objects", torch.isfinite(gt_depth)), ("clean_psnr_near_third", near_third_mask(gt_depth))):
        pixels = mask.expand_as(clean)
        result[key] = psnr(clean[pixels], gt_clean[pixels]) if bool(mask.any()) else float("nan")
    return result


def view_metrics(
    outputs: Mapping[str, Tensor],
    gt_rgb: Float[Tensor, "H W 3"],
    gt_clean: Optional[Float[Tensor, "H W 3"]] = None,
    gt_depth: Optional[Float[Tensor, "H W 1"]] = None,
    lpips: Optional[Callable] = None,
    linear_data: bool = True,
) -> Dict[str, float]:
    """Every metric of one rendered view (``outputs``: a camera render's ``[H, W, C]`` maps, in the
    data's colour space).

    * ``psnr``, ``ssim`` (and ``lpips`` when given) of ``rgb`` against the image in the medium;
    * with ``linear_data``: ``psnr_srgb``, the same PSNR after both are sRGB-encoded, i.e. on the
      image a viewer shows. Linear PSNR is dominated by the bright pixels; this one weighs the dark
      ones as the eye does, so a loss that favours one kind of pixel cannot win on one metric unseen;
    * with ``gt_depth`` (range, same units as ``depth``; ``inf`` for open water): ``depth_abs_rel``,
      its far third ``depth_abs_rel_far``, the median ``depth_abs_rel_median`` (robust to the few
      empty rays whose depth is the far plane), the signed bias ``depth_log_ratio_median`` (the
      median of ``log(depth / true)``: < 0 when surfaces sit too near), and the mean object
      opacity on object rays (``object_accumulation``) and on open water (``open_water_accumulation``: 0 where the object
      field leaves the open water empty, 0.5–0.6 on path-traced water);
    * with ``gt_clean`` and a ``clean`` output: ``clean_psnr``, ``clean_ssim``, on object pixels only
      when ``gt_depth`` says where open water is (it has no clean colour); then also
      :func:`clean_psnrs`: ``clean_psnr_objects`` (the same as ``clean_psnr``) and ``clean_psnr_near_third``;
    * ``mean_backscatter`` when there is a ``backscatter`` output.

    Abs-rel errors are ratios, so they do not depend on the depth unit.
    """
    rgb = outputs["rgb"].float().clamp(0.0, 1.0)
    gt_rgb = gt_rgb[..., :3].float()
    result: Dict[str, float] = {"psnr": psnr(rgb, gt_rgb), "ssim": ssim(rgb, gt_rgb)}
    if linear_data:
        result["psnr_srgb"] = psnr(linear_to_srgb(rgb), linear_to_srgb(gt_rgb))
    if lpips is not None:
        result["lpips"] = float(lpips(nchw(gt_rgb), nchw(rgb)))

    object_mask = None
    if gt_depth is not None:
        gt_depth = gt_depth.float()
        depth = outputs["depth"].float()
        object_mask = torch.isfinite(gt_depth)
        result["depth_abs_rel"] = depth_abs_rel(depth, gt_depth)
        result["depth_abs_rel_far"] = depth_abs_rel(depth, gt_depth, far_third_mask(gt_depth))
        accumulation = outputs.get("accumulation")
        if bool(object_mask.any()):
            rel = (depth[object_mask] - gt_depth[object_mask]).abs() / gt_depth[object_mask]
            result["depth_abs_rel_median"] = float(rel.contiguous().median())
            # Signed: the images fix optical depths beta * z, so a surface placed too near
            # (log ratio < 0) is paid for by a density too high by the same factor, and vice versa.
            # A true range of 0 (a surface at the lens) has no ratio: left out, never 0/0.
            positive = object_mask & (gt_depth > 0)
            if bool(positive.any()):
                ratio = depth[positive].clamp_min(0.0) / gt_depth[positive]
                result["depth_log_ratio_median"] = float(torch.log(ratio.clamp_min(1e-6)).contiguous().median())
            if accumulation is not None:
                result["object_accumulation"] = float(accumulation.float()[object_mask].mean())
        if accumulation is not None and bool((~object_mask).any()):
            result["open_water_accumulation"] = float(accumulation.float()[~object_mask].mean())

    if gt_clean is not None and "clean" in outputs:
        gt_clean = gt_clean[..., :3].float()
        clean = outputs["clean"].float().clamp(0.0, 1.0)
        if object_mask is not None:
            objects = object_mask.expand_as(clean)
            result["clean_psnr"] = psnr(clean[objects], gt_clean[objects])
            result["clean_ssim"] = ssim(torch.where(objects, clean, gt_clean), gt_clean)
            result.update(clean_psnrs(clean, gt_clean, gt_depth))
        else:
            result["clean_psnr"] = psnr(clean, gt_clean)
            result["clean_ssim"] = ssim(clean, gt_clean)
    if "backscatter" in outputs:
        result["mean_backscatter"] = float(outputs["backscatter"].float().mean())
    return result
