"""The GPU check: ``seathru-nerf`` (the full method, tiny-cuda-nn) and nerfacto matched to it,
trained one after the other on the water demo scene at a realistic resolution, on CUDA, for a
fixed number of iterations; one table of s/iteration, peak GPU memory, held-out PSNR (in the
water) and clean PSNR (against the scene without water; nerfacto's ``rgb`` is its clean image).

    .venv/bin/python scripts/gpu_check.py                      # 2000 iterations, 640x480, 20 views
    .venv/bin/python scripts/gpu_check.py --iterations 500 --output-dir /tmp/gpu_check

Without CUDA or tiny-cuda-nn it stops at once with one line saying which is missing (exit 1).

"Matched" nerfacto: every ``NerfactoModelConfig`` field of ``seathru-nerf`` (the rule of
:func:`seathru_nerfstudio.bench.methods.matched_nerfacto_config`, which matches the lite
method), the same rays per batch, optimisers, mixed precision and seed. Both runs evaluate
with :func:`seathru_nerfstudio.bench.worker.evaluate`, as ``seathru-bench`` does. Timings:
wall time of the training iterations (``torch.cuda.synchronize`` before each clock), no
evaluation inside; memory: ``torch.cuda.max_memory_allocated`` over each run.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

BIN = Path(sys.executable).parent


def missing_requirement() -> Optional[str]:
    """One line naming what this machine lacks for the check, or ``None``."""
    import torch

    if not torch.cuda.is_available():
        return (
            f"gpu_check: no CUDA GPU (torch {torch.__version__}, torch.cuda.is_available() is False); "
            "this check trains on an NVIDIA GPU"
        )
    try:
        import tinycudann  # noqa: F401
    except Exception as error:  # ImportError, or an OSError/RuntimeError from its CUDA extension
        return (
            f"gpu_check: tiny-cuda-nn is not usable ({type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}); "
            "install it: pip install git+https://github.com/NVlabs/tiny-cuda-nn/#subdirectory=bindings/torch"
        )
    return None


def matched_full_nerfacto(seathru: Any) -> Any:
    """nerfacto with every ``NerfactoModelConfig`` field of the ``seathru`` config (the fields
    :func:`matched_nerfacto_config` keeps nerfacto's own stay so), and its trainer settings."""
    from nerfstudio.models.nerfacto import NerfactoModelConfig
    from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

    from seathru_nerfstudio.bench.methods import MATCHED_NERFACTO_KEEPS_OWN, matched_nerfacto_config

    nerfacto_model = matched_nerfacto_config().pipeline.model
    for f in dataclasses.fields(NerfactoModelConfig):
        if f.name != "_target" and f.init and f.name not in MATCHED_NERFACTO_KEEPS_OWN:
            setattr(nerfacto_model, f.name, copy.deepcopy(getattr(seathru.pipeline.model, f.name)))
    config = copy.deepcopy(seathru)
    config.method_name = "nerfacto"
    config.pipeline = VanillaPipelineConfig(datamanager=config.pipeline.datamanager, model=nerfacto_model)
    return config


def train_and_measure(config: Any, scene: Path, out: Path, iterations: int, seed: int) -> Dict[str, Any]:
    """Train ``config`` on ``scene`` for ``iterations`` steps on CUDA; its figures."""
    import torch
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    from seathru_nerfstudio import metrics
    from seathru_nerfstudio.bench.worker import _load_truth, evaluate

    config.data = scene
    config.pipeline.datamanager.data = scene
    config.output_dir = out
    config.experiment_name = config.method_name
    config.timestamp = "gpu_check"
    config.vis = "tensorboard"
    config.machine.device_type = "cuda"
    config.machine.seed = seed
    config.max_num_iterations = iterations
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    with metrics.offline_lpips():
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
    pipeline = trainer.pipeline
    times: List[float] = []
    for step in range(iterations):
        torch.cuda.synchronize()
        start = time.perf_counter()
        with trainer.train_lock:
            pipeline.train()
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
            trainer.train_iteration(step)
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    peak = torch.cuda.max_memory_allocated()
    scale = float(pipeline.datamanager.train_dataparser_outputs.dataparser_scale)
    record = evaluate(pipeline, metrics.make_lpips(normalize=True), scale, _load_truth(scene))
    steady = sorted(times[len(times) // 10 :]) or times  # the first tenth compiles and warms up
    return {
        "method": config.method_name,
        "iterations": iterations,
        "sec_per_iter": sum(times) / len(times),
        "median_sec_per_iter": steady[len(steady) // 2],
        "peak_gpu_memory_gib": peak / 2**30,
        "psnr": record["metrics"].get("psnr"),
        "clean_psnr": record["metrics"].get("clean_psnr"),
        "medium": record.get("medium"),
    }


def table(rows: List[Dict[str, Any]], device: str) -> str:
    lines = [
        f"GPU check on {device}",
        "| method | iterations | s / iteration (mean, median) | peak GPU memory | PSNR | clean PSNR |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['iterations']} | {r['sec_per_iter']:.4f}, {r['median_sec_per_iter']:.4f} | "
            f"{r['peak_gpu_memory_gib']:.2f} GiB | {r['psnr']:.2f} dB | {r['clean_psnr']:.2f} dB |"
        )
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=2000, help="training iterations per method (default 2000)")
    parser.add_argument("--width", type=int, default=640, help="demo scene width (default 640)")
    parser.add_argument("--height", type=int, default=480, help="demo scene height (default 480)")
    parser.add_argument("--num-views", type=int, default=20, help="demo scene views; every 5th is held out")
    parser.add_argument("--seed", type=int, default=42, help="nerfstudio's machine.seed of both runs")
    parser.add_argument("--output-dir", type=Path, default=Path("outputs/gpu_check"), help="scene, runs and results.json")
    args = parser.parse_args(argv)
    missing = missing_requirement()
    if missing:
        print(missing, file=sys.stderr)
        return 1
    import torch

    from seathru_nerfstudio.config import seathru_nerf_config
    from seathru_nerfstudio.quiet import silence_upstream_warnings

    silence_upstream_warnings()
    scene = args.output_dir / f"demo-water-{args.width}x{args.height}"
    if not (scene / "transforms.json").is_file():
        subprocess.run(
            [str(BIN / "seathru-synth"), "--output-dir", str(scene), "--preset", "water", "--seed", "0",
             "--width", str(args.width), "--height", str(args.height), "--num-views", str(args.num_views)],
            check=True,
        )  # fmt: skip
    seathru = seathru_nerf_config()
    seathru.steps_per_eval_batch = seathru.steps_per_eval_image = seathru.steps_per_eval_all_images = 10**9
    seathru.steps_per_save = 10**9
    rows = []
    for config in (seathru, matched_full_nerfacto(seathru)):
        rows.append(train_and_measure(config, scene, args.output_dir / "runs", args.iterations, args.seed))
        print(f"gpu_check: {rows[-1]['method']}: {json.dumps(rows[-1], default=float)}", flush=True)
    device = f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}, CUDA {torch.version.cuda}"
    report = table(rows, device)
    print(report)
    (args.output_dir / "results.json").write_text(json.dumps({"device": device, "runs": rows}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
