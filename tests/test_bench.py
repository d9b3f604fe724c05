"""seathru-bench: metric functions on known answers, method specs, the report, and a tiny
end-to-end benchmark run (two methods, one tiny scene, a few iterations)."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import pytest
import torch

from seathru_nerfstudio import metrics
from seathru_nerfstudio.bench import report, scoring
from seathru_nerfstudio.bench.methods import (
    MAX_LABEL_CHARS,
    MethodSpecError,
    build_config,
    matched_nerfacto_config,
    method_label,
    override_flags,
    parse_spec,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------- metrics with known answers


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


# ---------------------------------------------------------------- methods


def test_method_spec_overrides_become_ns_train_flags():
    assert parse_spec("seathru-nerf-lite:quadrature=paper,medium_model=basic") == (
        "seathru-nerf-lite",
        {"quadrature": "paper", "medium_model": "basic"},
    )
    overrides = {
        "object_view_dependent": "false",
        "optimizers.medium.optimizer.lr": "0.05",
        "num_proposal_samples_per_ray": "16|8",
        "pipeline.datamanager.dataparser.eval_mode": "interval",
    }
    assert override_flags(overrides) == (
        [
            "--pipeline.model.object_view_dependent", "False",
            "--optimizers.medium.optimizer.lr", "0.05",
            "--pipeline.model.num_proposal_samples_per_ray", "16", "8",
        ],
        ["--eval_mode", "interval"],
    )  # fmt: skip


def test_method_spec_overrides_are_parsed_as_ns_train_parses_them(tmp_path):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    oracle = tmp_path / "medium.json"
    oracle.write_text("{}")  # the option checks that the file exists; the model reads it
    spec = (
        f"seathru-nerf-lite:quadrature=paper,object_view_dependent=false,pipeline.model.research.medium_oracle={oracle},"
        "num_proposal_samples_per_ray=16|8,optimizers.medium.optimizer.lr=0.123,"
        "pipeline.datamanager.train_num_rays_per_batch=256"
    )
    ours = build_config(spec)
    flags, _ = override_flags(parse_spec(spec)[1])
    assert ours == tyro.cli(AnnotatedBaseConfigUnion, args=["seathru-nerf-lite", *flags])  # ns-train's own parse
    model = ours.pipeline.model
    assert model.quadrature == "paper" and model.object_view_dependent is False
    assert model.research.medium_oracle == oracle and model.num_proposal_samples_per_ray == (16, 8)
    assert ours.optimizers["medium"]["optimizer"].lr == 0.123
    assert ours.pipeline.datamanager.train_num_rays_per_batch == 256
    assert build_config("seathru-nerf-lite").optimizers["medium"]["optimizer"].lr != 0.123  # a fresh config each time

    config = build_config("nerfacto:pipeline.datamanager.train_num_rays_per_batch=256,proposal_warmup=7")
    assert config.pipeline.datamanager.train_num_rays_per_batch == 256 and config.pipeline.model.proposal_warmup == 7
    config = build_config("seathru-nerf-lite:pipeline.datamanager.dataparser.eval_mode=interval,medium_model=basic")
    assert config.pipeline.datamanager.dataparser.eval_mode == "interval"
    assert type(config.pipeline.datamanager.dataparser) is type(build_config("seathru-nerf-lite").pipeline.datamanager.dataparser)
    # lower-case none is the clear-air medium model; None is None
    assert build_config("seathru-nerf-lite:medium_model=none").pipeline.model.medium_model == "none"
    assert build_config("seathru-nerf-lite:pipeline.model.research.medium_oracle=None").pipeline.model.research.medium_oracle is None


@pytest.mark.parametrize(
    "spec, reason",
    [
        ("seathru-nerf-lite:no_such_field=1", "Unrecognized options: --pipeline.model.no_such_field"),
        ("nerfacto:use_appearance_embedding=maybe", "invalid choice 'maybe'"),
        ("seathru-nerf-lite:num_nerf_samples_per_ray=1.5", "num-nerf-samples-per-ray"),
        ("seathru-nerf-lite:pipeline.datamanager.dataparser.no_such_field=1", "--no_such_field"),
        ("seathru-nerf-lite:quadrature", "not key=value"),
        ("no-such-method", "unknown method 'no-such-method'"),
    ],
)
def test_bad_method_specs_name_the_problem(spec, reason):
    with pytest.raises(MethodSpecError, match=re.escape(reason)):
        build_config(spec)


def test_bad_method_spec_stops_the_benchmark_before_anything_runs(tmp_path, monkeypatch, capsys):
    from seathru_nerfstudio.bench.cli import entrypoint

    argv = ["seathru-bench", "run", "--scenes", str(tmp_path / "none"), "--methods", "seathru-nerf-lite:no_such_field=1",
            "--output-dir", str(tmp_path / "bench")]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as stop:
        entrypoint()
    captured = capsys.readouterr()
    assert stop.value.code == 1 and "no_such_field" in " ".join((captured.out + captured.err).split())
    assert not (tmp_path / "bench").exists()


def test_matched_nerfacto_has_seathru_lite_capacity():
    from nerfstudio.models.nerfacto import NerfactoModelConfig
    from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

    from seathru_nerfstudio.config import seathru_nerf_lite_config
    from seathru_nerfstudio.model import SeathruModelConfig

    ours, theirs = seathru_nerf_lite_config(), matched_nerfacto_config()
    assert type(theirs.pipeline.model) is NerfactoModelConfig
    assert type(theirs.pipeline) is VanillaPipelineConfig  # SeathruPipeline drives a SeaThru model's controls
    assert not isinstance(theirs.pipeline.model, SeathruModelConfig)
    for name in (
        "implementation",
        "num_proposal_samples_per_ray",
        "num_nerf_samples_per_ray",
        "log2_hashmap_size",
        "num_levels",
        "max_res",
        "use_appearance_embedding",
        "distortion_loss_mult",
        "near_plane",
        "far_plane",
        "proposal_warmup",
        "average_init_density",
    ):
        assert getattr(theirs.pipeline.model, name) == getattr(ours.pipeline.model, name), name
    assert theirs.pipeline.model.camera_optimizer.mode == "off"
    assert theirs.pipeline.datamanager._target == ours.pipeline.datamanager._target
    assert theirs.pipeline.datamanager.train_num_rays_per_batch == ours.pipeline.datamanager.train_num_rays_per_batch
    assert theirs.optimizers.keys() == ours.optimizers.keys()


# ---------------------------------------------------------------- report (no training)


def _fake_results():
    def run(method, psnr, medium=True):
        evals = []
        for step, t in ((10, 5.0), (20, 10.0)):
            record = {
                "step": step,
                "train_time": t,
                "metrics": {"psnr": psnr + step / 10, "ssim": 0.5, "clean_psnr": 20.0, "depth_abs_rel": 0.3, "depth_abs_rel_far": 0.2},
            }
            if medium:
                record["medium_error"] = scoring.medium_error(
                    {"beta_D": [1.1, 1.0, 1.0], "beta_B": [1, 1, 1], "B_inf": [0.2, 0.2, 0.2]},
                    {"beta_D": [1.0, 1.0, 1.0], "beta_B": [1, 1, 1], "B_inf": [0.2, 0.2, 0.2]},
                )
            evals.append(record)
        return {"method": method, "scene": "water", "iterations": 20, "train_time": 10.0, "sec_per_iter": 0.5,
                "cpu_sec_per_iter": 0.4, "peak_rss_mb": 100.0, "evals": evals}

    return {"budget_kind": "seconds", "budget": 10.0, "machine": {"cpu_count": 2, "jobs": 2},
            "runs": [run("seathru-nerf-lite", 25.0), run("nerfacto", 24.0, medium=False)]}


def test_report_writes_table_and_plot(tmp_path):
    written = report.write_report(_fake_results(), tmp_path)
    table = written["table"].read_text()
    assert "| water | `seathru-nerf-lite` | 20 |" in table
    assert "27.00" in table  # final in-medium PSNR of seathru (25 + 20/10)
    assert "3% (10, 0, 0)" in table  # beta_D error: mean and per channel
    assert "| water | `nerfacto` |" in table and "n/a" in table
    assert "20.00" in table  # an older record's clean_psnr (object pixels) in the J PSNR objects column
    png = written["plot:water"].read_bytes()
    assert png.startswith(PNG_MAGIC) and len(png) > 10_000


# ---------------------------------------------------------------- tiny end-to-end run


def tiny_benchmark(root):
    """``seathru-bench run`` of two methods for 3 iterations on a tiny water scene, into ``root / "bench"``
    (``{"out", "proc"}``). Listed in ``BACKGROUND_JOBS``: the suite starts it at collection
    (conftest's ``background_job``)."""
    out = root / "bench"
    cmd = [
        sys.executable, "-m", "seathru_nerfstudio.bench.cli", "run",
        "--scenes", "water", "--methods", "seathru-nerf-lite", "nerfacto",
        "--output-dir", str(out), "--budget-iterations", "3", "--num-evals", "2",
        "--first-eval-fraction", "0.34", "--jobs", "2", "--width", "32", "--height", "24", "--num-views", "6",
        "--save-model",
    ]  # fmt: skip
    return {"out": out, "proc": subprocess.run(cmd, capture_output=True, text=True, timeout=600)}


BACKGROUND_JOBS = [tiny_benchmark]


@pytest.mark.slow  # trains through seathru-bench
def test_tiny_benchmark_run_end_to_end(background_job):
    job = background_job(tiny_benchmark)
    out, proc = job["out"], job["proc"]
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["failures"] == []
    assert results["budget_kind"] == "iterations" and results["budget"] == 3
    assert [r["method"] for r in results["runs"]] == ["seathru-nerf-lite", "nerfacto"]
    for run in results["runs"]:
        assert run["iterations"] == 3 and run["scene"] == "water"
        assert [e["step"] for e in run["evals"]] == [1, 3]
        assert run["train_time"] > 0 and run["sec_per_iter"] > 0 and run["peak_rss_mb"] > 100
        assert run["dataparser_scale"] > 0
        final = run["evals"][-1]["metrics"]
        for key in ("psnr", "ssim", "clean_psnr", "clean_psnr_objects", "clean_psnr_near_third", "clean_ssim", "depth_abs_rel", "depth_abs_rel_far"):
            assert math.isfinite(final[key]), key
        assert len(run["evals"][-1]["per_view"]) == 2  # views 0 and 5 of 6 are held out
    for label in ("seathru-nerf-lite", "nerfacto"):  # --save-model: what ns-eval and ns-render load
        (config_file,) = (out / "runs" / "water" / label).glob("run/*/*/config.yml")
        saved = sorted(p.name for p in config_file.parent.glob("nerfstudio_models/*.ckpt"))
        assert saved == ["step-000000001.ckpt", "step-000000003.ckpt"]  # one per evaluation
    seathru, nerfacto = results["runs"]
    top = results["ceilings"]["water"]["variants"]["ceiling"]["metrics"]  # the scene's ceiling, beside the runs
    assert math.isfinite(top["clean_psnr_objects"]) and math.isfinite(top["clean_psnr_near_third"])
    assert "medium_error_reference" in seathru["evals"][-1] and "medium_error_reference" not in nerfacto["evals"][-1]
    err = seathru["evals"][-1]["medium_error"]
    assert set(err) == {"beta_D", "beta_B", "B_inf"}
    assert err["beta_D"]["true"] == [1.3, 1.2, 0.9] and all(math.isfinite(x) for x in err["beta_D"]["rel"])
    assert "mean_backscatter" in seathru["evals"][-1]["metrics"]
    assert "medium_error" not in nerfacto["evals"][-1] and "mean_backscatter" not in nerfacto["evals"][-1]["metrics"]
    assert seathru["config"]["model"] == "SeathruModelConfig" and nerfacto["config"]["model"] == "NerfactoModelConfig"

    table = (out / "results.md").read_text()
    assert "| water | `seathru-nerf-lite` | 3 |" in table and "| water | `nerfacto` | 3 |" in table
    assert "| water | **ceiling: true z, true β_D, fitted β_B, B∞** |" in table
    png = (out / "bench_water.png").read_bytes()
    assert png.startswith(PNG_MAGIC) and len(png) > 10_000


def test_method_labels_fit_a_file_name_and_stay_unique(tmp_path):
    """A spec with many overrides once made a run directory name past the file system's limit."""
    overrides = ",".join(f"optimizers.medium_density.scheduler.option_{i}=0.00{i}" for i in range(8))
    long_a, long_b = f"seathru-nerf-lite:{overrides}", f"seathru-nerf-lite:{overrides}1"
    label_a, label_b = method_label(long_a), method_label(long_b)
    assert len(label_a) == MAX_LABEL_CHARS and label_a != label_b
    assert label_a == method_label(long_a)  # the same spec finds the same directory
    (tmp_path / label_a).mkdir()
    assert method_label("seathru-nerf-lite:medium_model=none") == "seathru-nerf-lite_medium_model_none"


def test_clear_air_prints_the_predicted_medium_not_an_error_against_a_fitted_reference():
    """Clear air's true medium is 0; its ceiling fits a tiny β_B there, and an error relative to that
    (2184% on the path-traced clear scene) says nothing: the cell shows the prediction. Where the truth
    is not 0, the reference's error stays."""
    zero = {key: [0.0, 0.0, 0.0] for key in scoring.MEDIUM_KEYS}
    pred = {"beta_D": [0.03, 0.05, 0.05], "beta_B": [0.028, 0.02, 0.02], "B_inf": [0.2, 0.3, 0.4]}
    fitted = {"beta_D": [0.0, 0.0, 0.0], "beta_B": [0.001, 0.001, 0.001], "B_inf": [0.3, 0.3, 0.3]}
    record = {"medium_error": scoring.medium_error(pred, zero), "medium_error_reference": scoring.medium_error(pred, fitted)}
    assert report._medium_cell(record, "beta_B") == "pred (0.028, 0.02, 0.02)"
    assert report._medium_cell(record, "beta_D") == "pred (0.03, 0.05, 0.05)"
    water = {"beta_D": [1.0, 1.0, 1.0], "beta_B": [1.0, 1.0, 1.0], "B_inf": [0.2, 0.2, 0.2]}
    record = {"medium_error": scoring.medium_error(pred, water), "medium_error_reference": scoring.medium_error(pred, fitted)}
    assert report._medium_cell(record, "B_inf") == report._medium_cell({"medium_error": record["medium_error_reference"]}, "B_inf")
    assert report._medium_cell(record, "B_inf") == "22% (33, 0, 33)"


def test_only_json_objects_with_an_event_are_events():
    """The runner reads its workers' stdout, where log lines appear too; a diagnostics line wrapped at
    the console's width once left ``1.00`` alone on a line, valid JSON, and the runner's reader died
    on it (``'float' object has no attribute 'get'``)."""
    from seathru_nerfstudio.bench.runner import parse_event

    assert parse_event('{"event": "progress", "step": 3}\n') == {"event": "progress", "step": 3}
    for line in ("1.00\n", "[1, 2]\n", '"text"\n', "null\n", '{"step": 3}\n', "seathru step 300: medium\n", "\n"):
        assert parse_event(line) is None, line


def test_an_exact_ceiling_has_no_gap():
    """Clear air's ceiling inverts nothing (``J = I``): its PSNR is the metric's floor of the error,
    200 dB, and a gap of −166 dB to it says nothing. A ceiling within the 16-bit data's precision
    prints "exact ceiling"; one below it keeps its gap."""
    from seathru_nerfstudio.metrics import psnr

    image = torch.rand(64, 64, 3, generator=torch.Generator().manual_seed(0))
    exact = psnr(image, image)
    rounded = psnr(torch.round(image * 65535.0) / 65535.0, image)  # the 16-bit data's own error
    assert exact > report.EXACT_CEILING_DB and abs(rounded - report.EXACT_CEILING_DB) < 1.0

    def results(ceiling_db: float) -> dict:
        scores = {"clean_psnr_objects": ceiling_db, "clean_psnr_near_third": ceiling_db}
        run = {"scene": "s", "method": "m", "evals": [{"metrics": {"clean_psnr_objects": 30.0, "clean_psnr_near_third": 31.0}}]}
        return {"ceilings": {"s": {"variants": {"ceiling": {"metrics": scores}}}}, "runs": [run]}

    assert report.ceiling_gaps(results(exact))[-1] == "| s | `m` | exact ceiling | exact ceiling |"
    assert report.ceiling_gaps(results(32.5))[-1] == "| s | `m` | -2.50 | -1.50 |"
