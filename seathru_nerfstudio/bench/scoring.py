"""The benchmark's metrics, as pure functions of tensors (tested on known answers).

Image metrics come from :mod:`seathru_nerfstudio.metrics` so that both methods are scored by
the same code as ``SeathruModel.get_image_metrics_and_images``.
"""

from __future__ import annotations

import math
from typing import Callable, Dict, List, Mapping, Optional, Sequence

import torch
from torch import Tensor

from seathru_nerfstudio import metrics

MEDIUM_KEYS = ("beta_D", "beta_B", "B_inf")
"""Ground-truth names (``ground_truth/medium.json``), matched to the model's outputs
``medium_attenuation`` (sigma_attn), ``medium_backscatter`` (sigma_bs) and ``medium_rgb`` (c_med)."""


def ssim(pred: Tensor, target: Tensor) -> float:
    """SSIM of two ``[H, W, 3]`` images with data range 1 (torchmetrics, as the model's)."""
    from torchmetrics.functional import structural_similarity_index_measure

    def nchw(x: Tensor) -> Tensor:
        return torch.moveaxis(x.float(), -1, 0)[None]

    return float(structural_similarity_index_measure(nchw(pred), nchw(target), data_range=1.0))


def medium_per_metre(
    medium_rgb: Tensor, sigma_attn: Tensor, sigma_bs: Tensor, dataparser_scale: float
) -> Dict[str, List[float]]:
    """Per-channel medians over rays of the model's medium, densities converted to 1/m.

    A density per scene unit is ``scale`` times a density per metre's worth of scene units:
    one metre is ``scale`` scene units, so ``beta [1/m] = sigma [1/unit] * scale``.
    """
    def med(x: Tensor) -> List[float]:
        # contiguous: torch.median(dim=0) of a stride-0 (expanded) view returns garbage (torch 2.14.1 CPU)
        return [float(v) for v in torch.median(x.reshape(-1, 3).float().contiguous(), dim=0).values]

    return {
        "beta_D": [v * dataparser_scale for v in med(sigma_attn)],
        "beta_B": [v * dataparser_scale for v in med(sigma_bs)],
        "B_inf": med(medium_rgb),
    }


def medium_error(
    predicted: Mapping[str, Sequence[float]], truth: Mapping[str, Sequence[float]]
) -> Dict[str, Dict[str, object]]:
    """Relative error per channel and its mean, for each of beta_D, beta_B and B_inf.

    ``rel = |pred - true| / true``; where the truth is 0 (clear air) the relative error is
    undefined (``nan``) and only ``abs = |pred - true|`` is meaningful.
    """
    out: Dict[str, Dict[str, object]] = {}
    for key in MEDIUM_KEYS:
        pred = [float(v) for v in predicted[key]]
        true = [float(v) for v in truth[key]]
        absolute = [abs(p - t) for p, t in zip(pred, true)]
        rel = [a / abs(t) if t != 0 else float("nan") for a, t in zip(absolute, true)]
        finite = [r for r in rel if math.isfinite(r)]
        out[key] = {
            "pred": pred,
            "true": true,
            "abs": absolute,
            "rel": rel,
            "rel_mean": sum(finite) / len(finite) if finite else float("nan"),
            "abs_mean": sum(absolute) / len(absolute),
        }
    return out


def view_metrics(
    outputs: Mapping[str, Tensor],
    batch: Mapping[str, Tensor],
    dataparser_scale: float,
    lpips: Optional[Callable] = None,
) -> Dict[str, float]:
    """Metrics of one held-out view. ``outputs``: the model's ``[H, W, C]`` maps; ``batch``:
    ``image`` and, when the scene has ground truth, ``gt_clean`` and ``gt_depth`` (scene units).

    A model without a ``clean`` output (nerfacto) is scored on its ``rgb`` as its clean image.
    Depths are converted to metres (divided by the dataparser scale) before the abs-rel, which
    does not change it (it is a ratio) but keeps every number in the record metric.
    """
    gt = batch["image"][..., :3].float()
    rgb = outputs["rgb"].float().clamp(0.0, 1.0)
    result: Dict[str, float] = {"psnr": metrics.psnr(rgb, gt), "ssim": ssim(rgb, gt)}
    if lpips is not None:
        def nchw(x: Tensor) -> Tensor:
            return torch.moveaxis(x, -1, 0)[None]

        result["lpips"] = float(lpips(nchw(gt), nchw(rgb)))

    object_mask = None
    gt_depth = batch.get("gt_depth")
    if gt_depth is not None:
        gt_m = gt_depth.float() / dataparser_scale
        pred_m = outputs["depth"].float() / dataparser_scale
        object_mask = torch.isfinite(gt_m)
        result["depth_abs_rel"] = metrics.depth_abs_rel(pred_m, gt_m)
        result["depth_abs_rel_far"] = metrics.depth_abs_rel(pred_m, gt_m, metrics.far_third_mask(gt_m))
        if bool(object_mask.any()):
            # robust to the few empty rays whose median depth is the far plane
            rel = (pred_m[object_mask] - gt_m[object_mask]).abs() / gt_m[object_mask]
            result["depth_abs_rel_median"] = float(rel.float().contiguous().median())
            if "accumulation" in outputs:
                result["object_accumulation"] = float(outputs["accumulation"].float()[object_mask].mean())
        if "accumulation" in outputs and bool((~object_mask).any()):
            # open water must stay empty: a wall of water colour there is a broken decomposition
            result["open_water_accumulation"] = float(outputs["accumulation"].float()[~object_mask].mean())
    gt_clean = batch.get("gt_clean")
    if gt_clean is not None:
        gt_clean = gt_clean[..., :3].float()
        clean = outputs.get("clean", outputs["rgb"]).float().clamp(0.0, 1.0)
        if object_mask is not None:  # open water has no clean colour: objects only
            mask3 = object_mask.expand_as(clean)
            result["clean_psnr"] = metrics.psnr(clean[mask3], gt_clean[mask3])
            result["clean_ssim"] = ssim(torch.where(mask3, clean, gt_clean), gt_clean)
        else:
            result["clean_psnr"] = metrics.psnr(clean, gt_clean)
            result["clean_ssim"] = ssim(clean, gt_clean)
    if "backscatter" in outputs:
        result["mean_backscatter"] = float(outputs["backscatter"].float().mean())
    return result


def mean_metrics(per_view: Sequence[Mapping[str, float]]) -> Dict[str, float]:
    """Mean over views of each metric (nan-aware: views where a metric is nan are skipped)."""
    keys = sorted({k for view in per_view for k in view})
    out = {}
    for key in keys:
        values = [float(v[key]) for v in per_view if key in v and math.isfinite(float(v[key]))]
        out[key] = sum(values) / len(values) if values else float("nan")
    return out


def log_spaced(budget: float, count: int, first_fraction: float = 1.0 / 32.0) -> List[float]:
    """``count`` points from ``budget * first_fraction`` to ``budget``, evenly in log."""
    if count <= 1:
        return [float(budget)]
    lo = math.log(budget * first_fraction)
    hi = math.log(budget)
    return [math.exp(lo + (hi - lo) * i / (count - 1)) for i in range(count)]
