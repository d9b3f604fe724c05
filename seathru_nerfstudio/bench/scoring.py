"""The benchmark's metrics, as pure functions of tensors (tested on known answers).

A view's image and depth metrics are :func:`seathru_nerfstudio.metrics.view_metrics`, the code
``SeathruModel.get_image_metrics_and_images`` uses, so both methods are scored as ``ns-eval``
scores ours; here: the medium against its ground truth, and averages over views.
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


MAX_LOG_FACTOR = 700.0
""":func:`backscatter_error_from_veil` caps ``s ln(B∞ / B∞_ref)`` here: ``e^700`` is finite in float64."""


def backscatter_error_from_veil(
    sensitivity: Sequence[float], veil: Sequence[float], reference_veil: Sequence[float]
) -> List[float]:
    """The relative error of ``β_B`` per channel that the veil's own error accounts for:
    ``(B∞ / B∞_ref)^s − 1``, ``s = d ln β_B / d ln B∞`` at the medium fit
    (:func:`~seathru_nerfstudio.medium_fit.veil_sensitivity`), linear in ``ln B∞``. What is left
    of a run's ``β_B`` error beyond it is the fit's own. ``nan`` where a veil is not positive."""
    return [
        math.expm1(min(s * math.log(v / r), MAX_LOG_FACTOR)) + 0.0 if v > 0 and r > 0 else float("nan")  # + 0.0: no -0
        for s, v, r in zip(sensitivity, veil, reference_veil)
    ]


def reference_errors(results: Dict[str, object]) -> None:
    """Give every evaluation with a medium its error against its scene's ceiling reference
    (``medium_error_reference``: β_D against the truth, β_B and B∞ against the ceiling's best
    fit; :mod:`seathru_nerfstudio.bench.ceiling_scene`), where ``results["ceilings"]`` has one.
    Where the run's medium fit recorded ``beta_B_per_B_inf``, also ``beta_B_error_from_veil``
    (:func:`backscatter_error_from_veil` against the reference veil). In place; doing it again
    changes nothing."""
    ceilings = results.get("ceilings") or {}
    for run in results.get("runs", []):  # type: ignore[union-attr]
        reference = (ceilings.get(run["scene"]) or {}).get("reference")  # type: ignore[union-attr]
        for record in run.get("evals", []) if reference else []:
            if record.get("medium") is not None:
                record["medium_error_reference"] = medium_error(record["medium"], reference)
                if record.get("beta_B_per_B_inf") is not None:
                    record["beta_B_error_from_veil"] = backscatter_error_from_veil(
                        record["beta_B_per_B_inf"], record["medium"]["B_inf"], reference["B_inf"]
                    )


def view_metrics(
    outputs: Mapping[str, Tensor], batch: Mapping[str, Tensor], lpips: Optional[Callable] = None
) -> Dict[str, float]:
    """Metrics of one held-out view (:func:`seathru_nerfstudio.metrics.view_metrics`, as
    ``ns-eval`` computes them). ``outputs``: the model's ``[H, W, C]`` maps; ``batch``: ``image``
    and, when the scene has ground truth, ``gt_clean`` and ``gt_depth``.

    A model without a ``clean`` output (nerfacto) is scored on its ``rgb`` as its clean image.
    """
    if "clean" not in outputs:
        outputs = {**outputs, "clean": outputs["rgb"]}
    return metrics.view_metrics(
        outputs, batch["image"], gt_clean=batch.get("gt_clean"), gt_depth=batch.get("gt_depth"), lpips=lpips
    )


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
