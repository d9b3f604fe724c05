"""One benchmark run (one method on one scene) in its own process.

``python -m seathru_nerfstudio.bench.worker SPEC.json`` trains with nerfstudio's ``Trainer``
stepped by hand, so the clock can be paused for evaluation, and writes the run's record to
``spec["output"]``. It prints one JSON line per event on stdout (progress, eval, done) for the
parent's progress bar; nerfstudio's own chatter goes to stderr.

Its own process per run keeps peak memory (``ru_maxrss``) per method, and gives every run a
fresh interpreter and data-loader process.

The training stack (nerfstudio's trainer, the methods, the metrics) is imported inside the
functions that use it: the data-loading worker the trainer spawns imports this module again as
``__mp_main__``, and needs none of it (on a 2-core CPU, alone: the modules it needs take about 2.7
CPU-s to import, this module with the training stack at its top 6.6).
"""

from __future__ import annotations

import json
import math
import platform
import random
import resource
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch


def _emit(event: str, **payload: Any) -> None:
    sys.stdout.write(json.dumps({"event": event, **payload}) + "\n")
    sys.stdout.flush()


def _peak_rss_mb() -> float:
    # Linux reports ru_maxrss in KiB (macOS in bytes).
    scale = 1.0 / 1024.0 if platform.system() != "Darwin" else 1.0 / (1024.0 * 1024.0)
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def _children_rss_mb() -> Optional[float]:
    try:
        import psutil
    except ImportError:
        return None
    return sum(c.memory_info().rss for c in psutil.Process().children(recursive=True)) / 2**20


def code_state() -> Dict[str, Any]:
    """The commit and the uncommitted changes of the package this process imported: a run on a
    tree that someone is editing is not a run of any commit, and the record must say so."""
    import hashlib
    import subprocess

    import seathru_nerfstudio

    root = Path(seathru_nerfstudio.__file__).resolve().parent
    state: Dict[str, Any] = {"package": str(root)}
    try:
        def git(*args: str) -> str:
            return subprocess.run(
                ["git", *args], cwd=root, capture_output=True, text=True, timeout=30, check=True
            ).stdout.rstrip()

        state["commit"] = git("rev-parse", "HEAD")
        dirty = [line[3:] for line in git("status", "--porcelain", "--untracked-files=no", "--", ".").splitlines()]
        state["dirty_files"] = dirty
        top = Path(git("rev-parse", "--show-toplevel"))
        state["dirty_sha256"] = {
            f: hashlib.sha256((top / f).read_bytes()).hexdigest()[:16] for f in dirty if (top / f).is_file()
        }
    except (OSError, subprocess.SubprocessError) as error:
        state["error"] = str(error)
    return state


def _seed(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _load_truth(scene: Path) -> Optional[Dict[str, List[float]]]:
    from seathru_nerfstudio.bench import scoring

    path = scene / "ground_truth" / "medium.json"
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    return {k: [float(v) for v in data[k]] for k in scoring.MEDIUM_KEYS}


@torch.no_grad()
def evaluate(pipeline, lpips, scale: float, truth) -> Dict[str, Any]:
    """Render every held-out view; image/depth metrics averaged over views, medium medians
    over all their rays. Metrics read the linear outputs (``rgb``, ``clean``, ...); there is no
    viewer here, so SeaThru's water controls are at their defaults, which change nothing."""
    from seathru_nerfstudio.bench import scoring

    model = pipeline.model
    dataset = pipeline.datamanager.eval_dataset
    model.eval()
    per_view = []
    media: Dict[str, List[torch.Tensor]] = {"medium_rgb": [], "medium_attenuation": [], "medium_backscatter": []}
    try:
        for i in range(len(dataset)):
            batch = dataset[i]
            camera = dataset.cameras[i : i + 1].to(model.device)
            outputs = model.get_outputs_for_camera(camera)
            per_view.append(scoring.view_metrics(outputs, batch, lpips))
            for key in media:
                if key in outputs:
                    media[key].append(outputs[key].reshape(-1, 3).cpu())
    finally:
        model.train()
    record: Dict[str, Any] = {"metrics": scoring.mean_metrics(per_view), "per_view": per_view}
    if hasattr(model, "medium_model"):  # the model in use: auto's choice once it has decided
        record["medium_model"] = model.medium_model
    if hasattr(model, "backscatter_veil_sensitivity") and bool((model.fit_backscatter_log_error >= 0).all()):
        record["beta_B_per_B_inf"] = [float(v) for v in model.backscatter_veil_sensitivity]  # at the medium fit
    if all(media.values()):
        # B∞ of the formation model is the veil in front of the surfaces (seathru_nerfstudio.surface_veil).
        surface_veil = getattr(getattr(model, "medium_field", None), "surface_veil", None)
        share = torch.ones(3) if surface_veil is None else surface_veil.detach().float().cpu()
        predicted = scoring.medium_per_metre(
            torch.cat(media["medium_rgb"]) * share,
            torch.cat(media["medium_attenuation"]),
            torch.cat(media["medium_backscatter"]),
            scale,
        )
        record["medium"] = predicted
        if truth is not None:
            record["medium_error"] = scoring.medium_error(predicted, truth)
    return record


def run(spec: Dict[str, Any]) -> Dict[str, Any]:
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    from seathru_nerfstudio import metrics
    from seathru_nerfstudio.bench.methods import build_config, parse_spec

    scene = Path(spec["scene_path"])
    run_dir = Path(spec["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    budget_kind = spec["budget_kind"]  # "seconds" or "iterations"
    budget = float(spec["budget"])
    eval_at = sorted(float(x) for x in spec["eval_at"])
    seed = int(spec.get("seed", 42))

    code = code_state()  # at start: what this process imports is what it runs
    torch.set_num_threads(int(spec["threads"])) if spec.get("threads") else None
    config = build_config(spec["method"])
    config.data = scene
    config.pipeline.datamanager.data = scene
    config.output_dir = run_dir
    config.experiment_name = "run"
    config.timestamp = "t"
    config.vis = "tensorboard"  # no viewer server; no event writer is set up either
    config.machine.seed = seed
    config.max_num_iterations = int(budget) if budget_kind == "iterations" else 10**9
    if spec.get("save_model"):
        config.save_only_latest_checkpoint = False
    _seed(seed)

    # nerfstudio's own models build LPIPS in populate_modules, which downloads AlexNet offline.
    with metrics.offline_lpips():
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
    if spec.get("save_model"):
        config.save_config()  # config.yml beside the checkpoints, as ns-train writes it
    lpips = metrics.make_lpips(normalize=True)
    pipeline = trainer.pipeline
    scale = float(pipeline.datamanager.train_dataparser_outputs.dataparser_scale)
    truth = _load_truth(scene)
    n_params = sum(p.numel() for p in pipeline.model.parameters())

    evals: List[Dict[str, Any]] = []
    iter_times: List[float] = []
    train_cpu = 0.0
    train_time = 0.0
    step = 0
    next_eval = 0
    last_progress = 0.0

    def clock() -> float:
        return train_time if budget_kind == "seconds" else float(step)

    while clock() < budget or next_eval < len(eval_at):
        if clock() >= budget and next_eval < len(eval_at):
            eval_at = eval_at[:next_eval] + [clock()]  # the budget point is always evaluated
        if next_eval < len(eval_at) and clock() >= eval_at[next_eval]:
            wall0 = time.perf_counter()
            record = evaluate(pipeline, lpips, scale, truth)
            record.update(
                step=step,
                train_time=train_time,
                train_cpu_time=train_cpu,
                eval_time=time.perf_counter() - wall0,
                sec_per_iter=train_time / step if step else float("nan"),
                median_sec_per_iter=float(np.median(iter_times[min(10, len(iter_times) // 10) :])) if iter_times else float("nan"),
                peak_rss_mb=_peak_rss_mb(),
            )
            evals.append(record)
            if spec.get("save_model"):
                trainer.save_checkpoint(step)  # one per evaluation: each point of the curve can be inspected
            _emit("eval", step=step, train_time=train_time, metrics=record["metrics"])
            next_eval += 1
            if clock() >= budget:
                break
            continue
        t0, c0 = time.perf_counter(), time.process_time()
        with trainer.train_lock:
            pipeline.train()
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
            loss, _, _ = trainer.train_iteration(step)
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        dt = time.perf_counter() - t0
        train_cpu += time.process_time() - c0
        if not math.isfinite(float(loss)):
            # SeathruTrainer skipped this step (and stops the run itself after too many in a row)
            _emit("warning", message=f"non-finite loss at step {step}: optimiser step skipped")
        iter_times.append(dt)
        train_time += dt
        step += 1
        if train_time - last_progress > 1.0 or budget_kind == "iterations":
            # SeaThru's decomposition diagnostics of the last batch (medium, open-water opacity)
            diagnostics = {k: float(v) for k, v in getattr(pipeline.model, "last_diagnostics", {}).items()}
            _emit("progress", step=step, train_time=train_time, loss=float(loss), diagnostics=diagnostics)
            last_progress = train_time

    result = {
        "method": spec["method"],
        "method_name": parse_spec(spec["method"])[0],
        "scene": spec["scene"],
        "scene_path": str(scene),
        "dataparser_scale": scale,
        "medium_truth": truth,
        "budget_kind": budget_kind,
        "budget": budget,
        "iterations": step,
        "train_time": train_time,
        "train_cpu_time": train_cpu,
        "cpu_sec_per_iter": train_cpu / step if step else float("nan"),
        "sec_per_iter": train_time / step if step else float("nan"),
        "median_sec_per_iter": float(np.median(iter_times[min(10, len(iter_times) // 10) :])) if iter_times else float("nan"),
        "peak_rss_mb": _peak_rss_mb(),
        "data_worker_rss_mb": _children_rss_mb(),
        "num_parameters": n_params,
        "code": code,
        "torch_threads": torch.get_num_threads(),
        "config": {
            "rays": config.pipeline.datamanager.train_num_rays_per_batch,
            "model": type(config.pipeline.model).__name__,
            "model_fields": {
                k: repr(v) for k, v in vars(config.pipeline.model).items() if not k.startswith("_")
            },
        },
        "evals": evals,
    }
    Path(spec["output"]).write_text(json.dumps(result, indent=1, default=float))
    _emit("done", output=spec["output"])
    return result


def _kill_children_on_sigterm() -> None:
    """A killed run must not leave its data-loader processes behind (they are daemons of
    this process, which only a normal interpreter exit would stop)."""
    import os
    import signal

    def handler(signum, frame):  # noqa: ARG001
        try:
            import psutil

            for child in psutil.Process().children(recursive=True):
                child.kill()
        finally:
            os._exit(128 + signum)

    signal.signal(signal.SIGTERM, handler)


def main(argv: Optional[List[str]] = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    _kill_children_on_sigterm()
    spec = json.loads(Path(argv[0]).read_text())
    try:
        run(spec)
    finally:
        # The parallel datamanager's loader processes are daemons; leave promptly.
        sys.stdout.flush()


if __name__ == "__main__":
    main()
    import os

    os._exit(0)
