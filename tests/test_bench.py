"""seathru-bench: method specs, the report, and a tiny end-to-end benchmark run (two methods, one
tiny scene, a few iterations); the metric functions are in test_bench_metrics.py."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import pytest
import torch

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
