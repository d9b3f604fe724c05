"""``seathru-bench run``: every method on every scene, under one training budget, one record.

Each (scene, method) run is a child process (:mod:`seathru_nerfstudio.bench.worker`); ``jobs``
of them run at once. With ``jobs`` equal to the number of methods, the methods of a scene
train side by side, so on a shared machine they see the same background load.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from nerfstudio.utils.rich_utils import CONSOLE
from seathru_nerfstudio.bench import scoring
from seathru_nerfstudio.bench.methods import build_config, method_label
from seathru_nerfstudio.data.io import write_text_atomic
from seathru_nerfstudio.quiet import child_environment

PRESETS = ("water", "fog", "none")


@dataclass
class RunConfig:
    """Train each method on each scene under the same budget; evaluate the held-out views at
    log-spaced points; write results.json, results.md and one plot per scene."""

    scenes: Tuple[str, ...] = ("water", "none")
    """Scenes: a demo preset (water, fog, none; generated into OUTPUT_DIR/scenes), a
    seathru-synth folder, or any nerfstudio dataset folder (with transforms.json)."""
    methods: Tuple[str, ...] = ("seathru-nerf-lite", "nerfacto")
    """Methods: seathru-nerf-lite, nerfacto (matched to seathru-nerf-lite), seathru-nerf, or any
    registered nerfstudio method, each with optional overrides, e.g.
    seathru-nerf-lite:quadrature=paper or seathru-nerf-lite:medium_model=basic."""
    output_dir: Path = Path("outputs/bench")
    """Where scenes, runs, results.json, results.md and the plots go."""
    budget_seconds: float = 480.0
    """Training wall time per run (evaluation excluded)."""
    budget_iterations: Optional[int] = None
    """If set, an iteration budget instead of --budget-seconds."""
    num_evals: int = 5
    """Evaluations per run, log-spaced up to the budget (the last one at the budget)."""
    first_eval_fraction: float = 1.0 / 16.0
    """The first evaluation happens at this fraction of the budget."""
    jobs: int = 1
    """Runs at once. Set it to the number of methods to train a scene's methods side by side."""
    threads: Optional[int] = None
    """torch threads per run (default: CPU cores // jobs, at least 1)."""
    seed: int = 42
    """Seed of every run (nerfstudio's machine.seed)."""
    width: int = 160
    """Width of generated preset scenes."""
    height: int = 120
    """Height of generated preset scenes."""
    num_views: int = 20
    """Views of generated preset scenes (every 5th is held out)."""
    scene_seed: int = 0
    """Seed of generated preset scenes."""
    save_model: bool = False
    """Also save each run's ``config.yml`` and a checkpoint at every evaluation (under
    ``runs/<scene>/<method>/run/``), so that ``ns-eval``, ``ns-render`` or the viewer can inspect
    any point of a benchmarked curve afterwards."""


def resolve_scene(scene: str, config: RunConfig) -> Tuple[str, Path]:
    """(name, folder) of a scene argument; presets are generated once and reused."""
    if scene in PRESETS and not Path(scene).exists():
        from seathru_nerfstudio.data.synthetic import SynthConfig, generate

        name = f"{scene}_{config.width}x{config.height}_{config.num_views}v_s{config.scene_seed}"
        folder = config.output_dir / "scenes" / name
        if not (folder / "transforms.json").is_file():
            generate(
                SynthConfig(
                    output_dir=folder,
                    preset=scene,  # type: ignore[arg-type]
                    seed=config.scene_seed,
                    width=config.width,
                    height=config.height,
                    num_views=config.num_views,
                    overwrite=True,
                )
            )
        return scene, folder.resolve()
    folder = Path(scene).expanduser()
    if not (folder / "transforms.json").is_file():
        raise SystemExit(f"seathru-bench: {scene!r} is neither a preset {PRESETS} nor a folder with transforms.json")
    return folder.name, folder.resolve()


def _machine_info() -> Dict[str, Any]:
    import torch

    return {
        "platform": platform.platform(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda": torch.cuda.is_available(),
        "loadavg_start": list(os.getloadavg()),
    }


class _LoadSampler(threading.Thread):
    """Samples the 1-minute load average, to document how busy the shared machine was."""

    def __init__(self, period: float = 10.0):
        super().__init__(daemon=True)
        self.period = period
        self.samples: List[Tuple[float, float]] = []
        self.stop = threading.Event()
        self.t0 = time.time()

    def run(self) -> None:
        while not self.stop.is_set():
            self.samples.append((time.time() - self.t0, os.getloadavg()[0]))
            self.stop.wait(self.period)


def _launch(spec: Dict[str, Any], spec_path: Path, log_path: Path) -> subprocess.Popen:
    """Start a worker: JSON events on its stdout (a pipe), everything else to ``log_path``, the
    known upstream warnings filtered (:mod:`seathru_nerfstudio.quiet`)."""
    write_text_atomic(spec_path, json.dumps(spec, indent=1))
    with open(log_path, "w") as log:  # the child keeps its own copy of the descriptor
        return subprocess.Popen(
            [sys.executable, "-m", "seathru_nerfstudio.bench.worker", str(spec_path)],
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            bufsize=1,
            env=child_environment(os.environ),
        )


def scene_ceilings(scenes: List[Tuple[str, Path]]) -> Dict[str, Any]:
    """The ceiling of each scene with ground truth (:func:`ceiling_scene.scene_ceiling`, seconds
    each), before any training, so that unreadable ground truth stops the benchmark early."""
    from seathru_nerfstudio.bench.ceiling_scene import NoGroundTruth, registration_line, scene_ceiling

    ceilings: Dict[str, Any] = {}
    for name, folder in scenes:
        try:
            ceilings[name] = scene_ceiling(folder, name)
        except NoGroundTruth:
            continue
        except ValueError as error:
            raise SystemExit(f"seathru-bench: the ceiling of {name}: {error}") from error
        top = ceilings[name]["variants"]["ceiling"]["metrics"]
        CONSOLE.print(
            f"ceiling of {name}: J PSNR {top['clean_psnr_objects']:.2f} dB over object pixels, "
            f"{top['clean_psnr_near_third']:.2f} dB on the nearest third"
        )
        poses = registration_line(ceilings[name]["registration"])
        if poses is not None:
            CONSOLE.print(f"{name}: {poses}")
    return ceilings


def parse_event(line: str) -> Optional[Dict[str, Any]]:
    """A worker's stdout line as an event (a JSON object with an ``event`` key), or ``None`` for any
    other line: the log lines nerfstudio and the model print there too, and a console line wrapped at
    the terminal's width can leave a bare number (``1.00``), which is valid JSON but no event."""
    try:
        event = json.loads(line)
    except json.JSONDecodeError:
        return None
    return event if isinstance(event, dict) and "event" in event else None


def run_benchmark(config: RunConfig) -> Dict[str, Any]:
    for method in config.methods:  # fail fast on a bad method or override, before writing anything
        build_config(method)
    out = config.output_dir
    out.mkdir(parents=True, exist_ok=True)
    scenes = [resolve_scene(s, config) for s in config.scenes]
    ceilings = scene_ceilings(scenes)
    if config.budget_iterations is not None:
        kind, budget = "iterations", float(config.budget_iterations)
        eval_at = sorted({round(x) for x in scoring.log_spaced(budget, config.num_evals, config.first_eval_fraction)})
    else:
        kind, budget = "seconds", float(config.budget_seconds)
        eval_at = scoring.log_spaced(budget, config.num_evals, config.first_eval_fraction)
    jobs = max(1, config.jobs)
    threads = config.threads or max(1, (os.cpu_count() or 1) // jobs)

    queue: List[Dict[str, Any]] = []
    for scene_name, folder in scenes:
        for method in config.methods:
            run_dir = out / "runs" / scene_name / method_label(method)
            run_dir.mkdir(parents=True, exist_ok=True)
            queue.append(
                {
                    "scene": scene_name,
                    "scene_path": str(folder),
                    "method": method,
                    "run_dir": str(run_dir),
                    "output": str(run_dir / "run.json"),
                    "budget_kind": kind,
                    "budget": budget,
                    "eval_at": eval_at,
                    "seed": config.seed,
                    "threads": threads,
                    "save_model": config.save_model,
                }
            )

    machine = _machine_info()
    machine.update(jobs=jobs, torch_threads_per_run=threads)
    sampler = _LoadSampler()
    sampler.start()
    failures: List[str] = []
    unit = "s" if kind == "seconds" else "it"
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f} " + unit),
        TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(),
        console=CONSOLE,
    ) as progress:
        tasks = {
            i: progress.add_task(f"{s['scene']:>8} {s['method']}", total=budget, status="queued")
            for i, s in enumerate(queue)
        }
        pending = list(range(len(queue)))
        running: Dict[int, Tuple[subprocess.Popen, threading.Thread]] = {}

        def pump(i: int, proc: subprocess.Popen) -> None:
            assert proc.stdout is not None
            with proc.stdout, open(Path(queue[i]["run_dir"]) / "events.jsonl", "w") as events:
                for line in proc.stdout:
                    events.write(line)
                    events.flush()
                    event = parse_event(line)
                    if event is None:
                        continue
                    done = event.get("train_time") if kind == "seconds" else event.get("step")
                    if event["event"] == "progress":
                        progress.update(tasks[i], completed=min(done, budget), status=f"step {event['step']}")
                    elif event["event"] == "eval":
                        m = event["metrics"]
                        progress.update(
                            tasks[i],
                            completed=min(done, budget),
                            status=f"step {event['step']} psnr {m.get('psnr', float('nan')):.2f}",
                        )

        while pending or running:
            while pending and len(running) < jobs:
                i = pending.pop(0)
                spec = queue[i]
                run_dir = Path(spec["run_dir"])
                proc = _launch(spec, run_dir / "spec.json", run_dir / "log.txt")
                thread = threading.Thread(target=pump, args=(i, proc), daemon=True)
                thread.start()
                running[i] = (proc, thread)
                progress.update(tasks[i], status="starting")
            for i, (proc, thread) in list(running.items()):
                if proc.poll() is not None:
                    thread.join(timeout=5)
                    del running[i]
                    if proc.returncode != 0 or not Path(queue[i]["output"]).is_file():
                        failures.append(f"{queue[i]['scene']} / {queue[i]['method']}: exit {proc.returncode}, see {queue[i]['run_dir']}/log.txt")
                        progress.update(tasks[i], status="[red]failed")
                    else:
                        progress.update(tasks[i], completed=budget, status="[green]done")
            time.sleep(0.5)

    sampler.stop.set()
    machine["loadavg_end"] = list(os.getloadavg())
    machine["loadavg_samples"] = sampler.samples
    runs = [json.loads(Path(s["output"]).read_text()) for s in queue if Path(s["output"]).is_file()]
    results = {
        "created": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": " ".join(sys.argv),
        "budget_kind": kind,
        "budget": budget,
        "eval_at": eval_at,
        "machine": machine,
        "scenes": {name: str(folder) for name, folder in scenes},
        "methods": list(config.methods),
        "failures": failures,
        "runs": runs,
        "ceilings": ceilings,
    }
    scoring.reference_errors(results)
    write_text_atomic(out / "results.json", json.dumps(results, indent=1, default=float))
    CONSOLE.print(f"seathru-bench: wrote {out / 'results.json'}")
    from seathru_nerfstudio.bench import report  # imported late: plotting is only needed here

    report.write_report(results, out)
    for failure in failures:
        CONSOLE.print(f"[red]failed: {failure}")
    return results
