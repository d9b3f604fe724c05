"""seathru-bench's scoring: metric functions on known answers (PSNR, depth errors, the medium's
errors against a reference, the veil's share of the backscatter error, per-view scores)."""

from __future__ import annotations

import math

import pytest
import torch

from seathru_nerfstudio import metrics
from seathru_nerfstudio.bench import report, scoring


def test_psnr_identical_images_is_capped_not_nan():
    image = torch.rand(8, 9, 3)
    value = metrics.psnr(image, image)
    assert math.isfinite(value) and value >= 190.0  # mse clamped at 1e-20 -> 200 dB


@pytest.mark.parametrize("offset", [0.5, 0.1, 0.01])
def test_psnr_known_offset(offset):
    target = torch.full((6, 7, 3), 0.25)
    assert metrics.psnr(target + offset, target) == pytest.approx(-10 * math.log10(offset**2), abs=1e-3)


@pytest.mark.parametrize("k", [0.5, 1.0, 1.25, 3.0])
def test_depth_abs_rel_known_scale(k):
    gt = torch.linspace(1.0, 5.0, 40).reshape(5, 8, 1)
    gt[0, 0, 0] = float("inf")  # open water is ignored
    assert metrics.depth_abs_rel(gt.clamp_max(10) * k, gt) == pytest.approx(abs(k - 1), abs=1e-6)
    far = metrics.far_third_mask(gt)
    assert metrics.depth_abs_rel(gt.clamp_max(10) * k, gt, far) == pytest.approx(abs(k - 1), abs=1e-6)


def test_far_third_mask_takes_the_farthest_third_and_no_open_water():
    gt = torch.arange(1, 31, dtype=torch.float32).reshape(5, 6, 1)
    gt[0, 0, 0] = float("inf")
    mask = metrics.far_third_mask(gt)
    finite = gt[torch.isfinite(gt)]
    assert not bool(mask[0, 0, 0])
    assert int(mask.sum()) == pytest.approx(len(finite) / 3, abs=1)
    assert float(gt[mask].min()) >= float(torch.quantile(finite, 2 / 3))


def test_medium_error_against_known_parameters():
    truth = {"beta_D": [1.0, 2.0, 4.0], "beta_B": [0.5, 0.5, 0.5], "B_inf": [0.1, 0.2, 0.4]}
    pred = {"beta_D": [1.1, 1.8, 4.0], "beta_B": [0.5, 0.5, 0.5], "B_inf": [0.05, 0.3, 0.4]}
    err = scoring.medium_error(pred, truth)
    assert err["beta_D"]["rel"] == pytest.approx([0.1, 0.1, 0.0])
    assert err["beta_D"]["rel_mean"] == pytest.approx(0.2 / 3)
    assert err["beta_B"]["rel_mean"] == pytest.approx(0.0)
    assert err["B_inf"]["rel"] == pytest.approx([0.5, 0.5, 0.0])
    assert err["B_inf"]["abs"] == pytest.approx([0.05, 0.1, 0.0])


def test_medium_error_in_clear_air_has_no_relative_error():
    zero = {k: [0.0, 0.0, 0.0] for k in scoring.MEDIUM_KEYS}
    pred = {k: [0.1, 0.2, 0.3] for k in scoring.MEDIUM_KEYS}
    err = scoring.medium_error(pred, zero)
    assert all(math.isnan(r) for r in err["beta_D"]["rel"]) and math.isnan(err["beta_D"]["rel_mean"])
    assert err["beta_D"]["abs_mean"] == pytest.approx(0.2)


def test_the_veils_share_of_the_backscatter_error_is_its_error_to_the_sensitivity():
    """``(B∞ / B∞_ref)^s − 1``: one for one at ``s = −1`` (a veil 10% high, β_B 1/1.1 of the truth),
    nothing at ``s = 0`` or under the right veil, squared at ``s = −2``; undefined without a veil.
    The bench puts it beside each run's β_B error against the scene's reference."""
    explained = scoring.backscatter_error_from_veil([-1.0, 0.0, -2.0], [0.22, 0.3, 0.05], [0.2, 0.1, 0.1])
    assert explained == pytest.approx([1 / 1.1 - 1, 0.0, 3.0])
    assert scoring.backscatter_error_from_veil([-3.0], [0.4], [0.4]) == [0.0]
    assert math.isnan(scoring.backscatter_error_from_veil([-1.0], [0.0], [0.2])[0])
    assert math.isfinite(scoring.backscatter_error_from_veil([-60.0], [1e-12], [0.5])[0])  # capped, not an overflow
    medium = {"beta_D": [1.0, 1.0, 1.0], "beta_B": [0.5, 0.8, 1.0], "B_inf": [0.22, 0.2, 0.2]}
    reference = {"beta_D": [1.0, 1.0, 1.0], "beta_B": [1.0, 1.0, 1.0], "B_inf": [0.2, 0.2, 0.2]}
    record = {"medium": medium, "beta_B_per_B_inf": [-5.0, -1.0, -1.0]}
    results = {"ceilings": {"reef": {"reference": reference}}, "runs": [{"scene": "reef", "method": "m", "evals": [record]}]}
    scoring.reference_errors(results)
    assert record["beta_B_error_from_veil"] == pytest.approx([1.1**-5 - 1, 0.0, 0.0])
    (line,) = report.veil_lines(results)[2:]
    assert line == "| reef | `m` | -50, -20, +0 | +10, +0, +0 | -5.00, -1.00, -1.00 | -38, +0, +0 |"
    assert report.veil_lines({"runs": [{"scene": "reef", "method": "m", "evals": [{"medium": medium}]}]}) == []
    clear = {"medium": medium, "beta_B_per_B_inf": [-1.0, -1.0, -1.0], "beta_B_error_from_veil": [0.1, 0.0, 0.0],
             "medium_error": scoring.medium_error(medium, {k: [0.0, 0.0, 0.0] for k in scoring.MEDIUM_KEYS})}
    (line,) = report.veil_lines({"runs": [{"scene": "air", "method": "m", "evals": [clear]}]})[2:]
    assert "n/a, n/a, n/a" in line  # no relative error against a zero truth


def test_medium_per_metre_converts_densities_with_the_dataparser_scale_and_takes_medians():
    # 101 rays; medians 0.5 (sigma per scene unit), scale 0.25 scene units per metre -> 0.125/m.
    rays = torch.linspace(0.0, 1.0, 101)[:, None].expand(101, 3)
    c_med = torch.tensor([0.1, 0.2, 0.3]).expand(101, 3)
    out = scoring.medium_per_metre(c_med, rays * 1.0, rays * 2.0, dataparser_scale=0.25)
    assert out["beta_D"] == pytest.approx([0.125] * 3)
    assert out["beta_B"] == pytest.approx([0.25] * 3)
    assert out["B_inf"] == pytest.approx([0.1, 0.2, 0.3])


def test_view_metrics_scores_nerfacto_rgb_as_its_clean_image_and_objects_only():
    h, w = 24, 32
    gt = torch.full((h, w, 3), 0.3)
    gt_clean = torch.full((h, w, 3), 0.6)
    depth = torch.full((h, w, 1), 2.0)
    depth[:4] = float("inf")  # open water rows: no clean colour, no depth
    batch = {"image": gt, "gt_clean": gt_clean, "gt_depth": depth}
    outputs = {"rgb": gt + 0.1, "depth": depth.clamp_max(5) * 1.5}
    m = scoring.view_metrics(outputs, batch)
    assert m["psnr"] == pytest.approx(20.0, abs=1e-3)

    def srgb(v):  # IEC 61966-2-1, above the linear toe
        return 1.055 * v ** (1 / 2.4) - 0.055

    assert m["psnr_srgb"] == pytest.approx(-20 * math.log10(srgb(0.4) - srgb(0.3)), abs=1e-3)
    assert m["clean_psnr"] == pytest.approx(-10 * math.log10(0.2**2), abs=1e-3)  # rgb 0.4 vs 0.6
    assert m["clean_psnr_objects"] == m["clean_psnr"]
    assert m["depth_abs_rel"] == pytest.approx(0.5, abs=1e-6)
    assert m["depth_abs_rel_far"] == pytest.approx(0.5, abs=1e-6)
    assert m["depth_abs_rel_median"] == pytest.approx(0.5, abs=1e-6)
    assert m["depth_log_ratio_median"] == pytest.approx(math.log(1.5), abs=1e-6)  # 1.5x too far
    outputs["depth"] = depth.clamp_max(5) * 0.5
    assert scoring.view_metrics(outputs, batch)["depth_log_ratio_median"] == pytest.approx(math.log(0.5), abs=1e-6)
    outputs["depth"] = torch.zeros_like(depth)  # no surface at all: a large but finite bias
    assert math.isfinite(scoring.view_metrics(outputs, batch)["depth_log_ratio_median"])
    at_lens = {**batch, "gt_depth": torch.where(torch.isfinite(depth), torch.zeros_like(depth), depth)}
    assert "depth_log_ratio_median" not in scoring.view_metrics(outputs, at_lens)  # no 0/0 ratio
    half = depth.clone()
    half[4:14] = 0.0  # half the object rays at the lens: the median of the others, finite
    assert scoring.view_metrics(outputs, {**batch, "gt_depth": half})["depth_log_ratio_median"] == pytest.approx(-13.8155, abs=1e-3)
    outputs["depth"] = depth.clamp_max(5) * 1.5
    assert "mean_backscatter" not in m and "object_accumulation" not in m
    accumulation = torch.ones(h, w, 1)
    accumulation[:4] = 0.25  # a haze of opacity over the open water
    outputs.update(clean=gt_clean.clone(), backscatter=torch.full((h, w, 3), 0.02), accumulation=accumulation)
    m = scoring.view_metrics(outputs, batch)
    assert m["clean_psnr"] >= 190 and m["mean_backscatter"] == pytest.approx(0.02)
    assert m["object_accumulation"] == pytest.approx(1.0) and m["open_water_accumulation"] == pytest.approx(0.25)


def test_clean_psnr_on_object_pixels_and_their_nearest_third():
    """Rows 0-2 open water, rows 3-8 objects at a range equal to the row: the nearest third of the
    72 object pixels is rows 3-4, off by 0.1; the far rows are off by 0.2; open water by 0.5."""
    h, w = 9, 12  # SSIM's 11-pixel window needs 6 pixels a side
    depth = torch.arange(h, dtype=torch.float32)[:, None, None].expand(h, w, 1).clone()
    depth[:3] = float("inf")
    gt_clean = torch.full((h, w, 3), 0.5)
    error = torch.full((h, w, 1), 0.2)
    error[:3], error[3:5] = 0.5, 0.1
    batch = {"image": gt_clean, "gt_clean": gt_clean, "gt_depth": depth}
    m = scoring.view_metrics({"rgb": gt_clean, "clean": gt_clean + error, "depth": depth.clamp_max(9)}, batch)
    assert m["clean_psnr_near_third"] == pytest.approx(20.0, abs=1e-4)
    assert m["clean_psnr_objects"] == pytest.approx(-10 * math.log10((24 * 0.1**2 + 48 * 0.2**2) / 72), abs=1e-4)
    scaled = scoring.view_metrics({"rgb": gt_clean, "clean": gt_clean + error, "depth": depth}, {**batch, "gt_depth": depth * 7})
    assert scaled["clean_psnr_near_third"] == m["clean_psnr_near_third"]  # by rank: any range unit


def test_model_and_bench_score_a_view_with_the_same_code():
    """ns-eval (SeathruModel.get_image_metrics_and_images) and the benchmark report the same numbers."""
    from tiny_training import tiny_model

    gen = torch.Generator().manual_seed(0)
    h, w = 16, 20
    depth = 1.0 + torch.rand(h, w, 1, generator=gen)
    gt_depth = depth * (1 + 0.2 * torch.rand(h, w, 1, generator=gen))
    gt_depth[:3] = float("inf")
    outputs = {k: torch.rand(h, w, 3, generator=gen) for k in ("rgb", "clean", "backscatter")}
    outputs.update(depth=depth, accumulation=torch.rand(h, w, 1, generator=gen))
    batch = {k: torch.rand(h, w, 3, generator=gen) for k in ("image", "gt_clean")}
    batch["gt_depth"] = gt_depth
    model_scores, _ = tiny_model().get_image_metrics_and_images(outputs, batch)
    assert model_scores == scoring.view_metrics(outputs, batch)
    assert {"psnr", "psnr_srgb", "ssim", "clean_psnr", "clean_ssim", "depth_abs_rel", "depth_abs_rel_median"} <= set(
        model_scores
    )


def test_mean_metrics_skips_nan_and_log_spaced_ends_at_budget():
    assert scoring.mean_metrics([{"a": 1.0}, {"a": float("nan")}, {"a": 3.0}])["a"] == 2.0
    points = scoring.log_spaced(480.0, 5, 1 / 16)
    assert points[0] == pytest.approx(30.0) and points[-1] == pytest.approx(480.0)
    assert all(b / a == pytest.approx(2.0) for a, b in zip(points, points[1:]))
