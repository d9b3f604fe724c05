"""Markdown table and plots of a ``results.json`` (``seathru-bench run`` / ``report``), each
scene's ceiling (:mod:`seathru_nerfstudio.bench.ceiling_scene`) beside its runs."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from seathru_nerfstudio.bench import scoring

EXACT_CEILING_DB = 10.0 * math.log10(12.0 * 65535.0**2)
"""107.2 dB, the PSNR of rounding a linear image to 16 bits (error variance ``(1/65535)² / 12``): a
ceiling above it reproduces ``J`` to the data's own precision (clear air, where ``J = I``), so
there is no gap to it worth printing."""

# (key in an eval record, column title, better: "high"/"low", format)
IMAGE_COLUMNS: List[Tuple[str, str, str, str]] = [
    ("psnr", "PSNR", "high", "{:.2f}"),
    ("ssim", "SSIM", "high", "{:.3f}"),
    ("lpips", "LPIPS", "low", "{:.3f}"),
    ("clean_psnr_objects", "J PSNR objects", "high", "{:.2f}"),
    ("clean_psnr_near_third", "J PSNR near third", "high", "{:.2f}"),
    ("clean_ssim", "clean SSIM", "high", "{:.3f}"),
    ("depth_abs_rel_median", "depth abs-rel median", "low", "{:.3f}"),
    ("depth_abs_rel", "depth abs-rel mean", "low", "{:.3f}"),
    ("depth_abs_rel_far", "far-third abs-rel", "low", "{:.3f}"),
    ("mean_backscatter", "mean backscatter", "low", "{:.4f}"),
]
MEDIUM_COLUMNS = [("beta_D", "β_D err"), ("beta_B", "β_B err"), ("B_inf", "B∞ err")]
ALIASES = {"clean_psnr_objects": "clean_psnr"}
"""A metric's name in results.json files written before it had this one (``clean_psnr`` was
already over the object pixels where the scene had a true range)."""
CEILING_SCORES = ("clean_psnr_objects", "clean_psnr_near_third")

PLOTTED: List[Tuple[str, str, bool]] = [
    ("psnr", "in-medium PSNR (dB) ↑", False),
    ("clean_psnr_objects", "J PSNR, object pixels (dB) ↑", False),
    ("clean_psnr_near_third", "J PSNR, nearest third (dB) ↑", False),
    ("ssim", "SSIM ↑", False),
    ("depth_abs_rel_median", "depth abs-rel median ↓", True),
    ("depth_abs_rel", "depth abs-rel mean ↓", True),
    ("depth_abs_rel_far", "far-third depth abs-rel ↓", True),
    ("medium:beta_D", "β_D mean rel. error ↓", True),
    ("medium:beta_B", "β_B mean rel. error ↓", True),
    ("medium:B_inf", "B∞ mean rel. error ↓", True),
    ("mean_backscatter", "mean backscatter ↓", False),
]


def _metric(metrics: Dict[str, Any], key: str) -> Optional[float]:
    value = metrics.get(key, metrics.get(ALIASES.get(key, key)))
    return None if value is None else float(value)


def _no_true_medium(err: Dict[str, Any]) -> bool:
    """Whether an error record's truth is 0 in every channel (clear air): no relative error exists."""
    return all(isinstance(r, float) and math.isnan(r) for r in err["rel"])


def _medium_errors(record: Dict[str, Any]) -> Dict[str, Any]:
    """Against the scene's ceiling reference where there is one, else against the truth; per
    quantity, the truth where it is 0 (clear air: a reference fitted there is a tiny number, and
    a relative error against it says nothing)."""
    truth = record.get("medium_error") or {}
    reference = record.get("medium_error_reference") or truth
    return {key: truth[key] if key in truth and _no_true_medium(truth[key]) else err for key, err in reference.items()}


def _value(record: Dict[str, Any], key: str) -> float:
    if key.startswith("medium:"):
        err = _medium_errors(record).get(key.split(":", 1)[1])
        if not err:
            return float("nan")
        value = err["rel_mean"]
        return float(value) if value is not None else float("nan")
    value = _metric(record.get("metrics", {}), key)
    return float("nan") if value is None else value


def _fmt(value: Optional[float], fmt: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    return fmt.format(value)


def _values(values) -> str:
    return "(" + ", ".join(f"{v:.3g}" for v in values) + ")"


def _medium_cell(record: Dict[str, Any], key: str) -> str:
    err = _medium_errors(record).get(key)
    if err is None:
        medium = record.get("medium")
        if medium is None:
            return "n/a"
        return _values(medium[key])
    if _no_true_medium(err):  # truth is 0: absolute values
        return "pred " + _values(err["pred"])
    return f"{100 * err['rel_mean']:.0f}% (" + ", ".join(f"{100 * r:.0f}" for r in err["rel"]) + ")"


def ceiling_rows(record: Dict[str, Any], before: int) -> List[List[str]]:
    """A scene's ceiling variants as rows of the results table: ``before`` empty cells (the
    run's cost), then the J scores; the medium cells give the fixed β_D (the truth) and the
    fitted values, and for the variant that fits β_D too, its errors against the reference."""
    rows = []
    for key, variant in record.get("variants", {}).items():
        row = [record["scene"], f"**{variant['label']}**"] + ["–"] * before
        row += [
            _fmt(_metric(variant["metrics"], k), fmt) if k in CEILING_SCORES else "–" for k, _, _, fmt in IMAGE_COLUMNS
        ]
        if key == "ceiling":
            medium = variant["medium"]
            row += ["true " + _values(medium["beta_D"]), "fit " + _values(medium["beta_B"]), "fit " + _values(medium["B_inf"])]
        else:
            row += [_medium_cell(variant, k) for k, _ in MEDIUM_COLUMNS]
        rows.append(row)
    return rows


def ceiling_table(record: Dict[str, Any]) -> str:
    """One scene's ceiling as markdown (``seathru-bench ceiling``): J scores per variant, the
    fitted medium, its error against the truth (``ground_truth/medium.json``), the fit residual."""
    lines = [
        f"Ceiling of {record['scene']} ({record['scene_path']}): medium fitted on {len(record['fit_views'])} "
        f"{record['fit_split']} views ({record['fit']['num_pixels']} object pixels), J scored on "
        f"{len(record['held_out_views'])} held-out views.",
        "",
        "| variant | J PSNR objects | J PSNR near third | β_D | β_B | B∞ | fit rms | capped gains |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for variant in record["variants"].values():
        m, medium = variant["metrics"], variant["medium"]
        lines.append(
            f"| {variant['label']} | {_fmt(_metric(m, 'clean_psnr_objects'), '{:.2f}')} | "
            f"{_fmt(_metric(m, 'clean_psnr_near_third'), '{:.2f}')} | {_values(medium['beta_D'])} | "
            f"{_values(medium['beta_B'])} | {_values(medium['B_inf'])} | {_values(medium['rms'])} | {variant['capped_gains']} |"
        )
    truth = record["truth"]
    lines.append(f"| truth (medium.json) | | | {_values(truth['beta_D'])} | {_values(truth['beta_B'])} | {_values(truth['B_inf'])} | | |")
    error = record["fit_vs_truth"]
    lines += [
        "",
        "Best fit against the truth: β_B " + _medium_cell({"medium_error": error}, "beta_B")
        + ", B∞ " + _medium_cell({"medium_error": error}, "B_inf")
        + "; fitting β_D too: β_D " + _medium_cell({"medium_error": scoring.medium_error(record["fit_all"], truth)}, "beta_D") + ".",
        "",
        record["note"],
    ]
    return "\n".join(lines) + "\n"


def ceiling_gaps(results: Dict[str, Any]) -> List[str]:
    """Each run's final J scores minus its scene's ceiling (dB; ≤ 0 unless a method beats the
    model's inversion), as markdown lines. Where the inversion is exact (above
    :data:`EXACT_CEILING_DB`; clear air, where ``J = I``) there is no gap to measure, and the cell says so."""
    ceilings = results.get("ceilings") or {}
    lines = ["| scene | method | J objects − ceiling | J near third − ceiling |", "|---|---|---|---|"]
    for run in results.get("runs", []):
        record = ceilings.get(run["scene"])
        if not record or not run.get("evals"):
            continue
        final, top = run["evals"][-1].get("metrics", {}), record["variants"]["ceiling"]["metrics"]
        gaps = []
        for key in CEILING_SCORES:
            ours, best = _metric(final, key), _metric(top, key)
            if best is not None and best >= EXACT_CEILING_DB:
                gaps.append("exact ceiling")
                continue
            gaps.append(_fmt(None if ours is None or best is None else ours - best, "{:+.2f}"))
        lines.append(f"| {run['scene']} | `{run['method']}` | {gaps[0]} | {gaps[1]} |")
    return lines if len(lines) > 2 else []


def veil_lines(results: Dict[str, Any]) -> List[str]:
    """Each run's final β_B error beside the part of it that its veil's error accounts for
    (``beta_B_error_from_veil``), as markdown lines; none where no run recorded it."""
    lines = ["| scene | method | β_B error (R, G, B %) | B∞ error | β_B per B∞ at the fit | accounted for by the veil (%) |", "|---|---|---|---|---|---|"]
    for run in results.get("runs", []):
        final = run["evals"][-1] if run.get("evals") else {}
        explained = final.get("beta_B_error_from_veil")
        errors = _medium_errors(final)
        if explained is None or "beta_B" not in errors:
            continue
        signed, veil = ([100 * (p - t) / t if t else float("nan") for p, t in zip(errors[key]["pred"], errors[key]["true"])] for key in ("beta_B", "B_inf"))
        cells = [", ".join(_fmt(v, "{:+.0f}") for v in values) for values in (signed, veil)]
        lines.append(
            f"| {run['scene']} | `{run['method']}` | {cells[0]} | {cells[1]} | "
            + ", ".join(f"{v:.2f}" for v in final["beta_B_per_B_inf"]) + " | "
            + ", ".join(_fmt(100 * v, "{:+.0f}") for v in explained) + " |"
        )
    return lines if len(lines) > 2 else []


def markdown_table(results: Dict[str, Any]) -> str:
    """Final-evaluation table (one row per scene x method) and the per-evaluation curves."""
    unit = "s" if results.get("budget_kind") == "seconds" else "iterations"
    machine = results.get("machine", {})
    lines = [
        f"Budget: {results.get('budget'):.0f} {unit} of training per run; "
        f"{machine.get('cpu_count')} CPU cores, torch {machine.get('torch')}, "
        f"{machine.get('jobs', 1)} run(s) at once with {machine.get('torch_threads_per_run')} torch thread(s) each; "
        f"load average {machine.get('loadavg_start', [float('nan')])[0]:.1f} at start, "
        f"{machine.get('loadavg_end', [float('nan')])[0]:.1f} at end.",
        "",
    ]
    scoring.reference_errors(results)
    head = ["scene", "method", "iters", "train s", "s/iter", "CPU s/iter", "peak RSS MB"]
    head += [title for _, title, _, _ in IMAGE_COLUMNS]
    head += [title for _, title in MEDIUM_COLUMNS]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    ceilings = results.get("ceilings") or {}
    shown = set()
    for run in results.get("runs", []):
        if run["scene"] in ceilings and run["scene"] not in shown:
            lines += ["| " + " | ".join(row) + " |" for row in ceiling_rows(ceilings[run["scene"]], 5)]
        shown.add(run["scene"])
        final = run["evals"][-1] if run.get("evals") else {}
        row = [
            run["scene"],
            f"`{run['method']}`",
            str(run["iterations"]),
            f"{run['train_time']:.0f}",
            f"{run['sec_per_iter']:.2f}",
            _fmt(run.get("cpu_sec_per_iter"), "{:.2f}"),
            f"{run['peak_rss_mb']:.0f}",
        ]
        row += [_fmt(_metric(final.get("metrics", {}), key), fmt) for key, _, _, fmt in IMAGE_COLUMNS]
        row += [_medium_cell(final, key) for key, _ in MEDIUM_COLUMNS]
        lines.append("| " + " | ".join(row) + " |")
    lines += [
        "",
        "Medium errors: mean relative error over RGB (per channel in brackets, %) of the median "
        "over held-out rays, densities converted to 1/m; where the truth is 0, the predicted values. "
        "β_D is compared with the truth; β_B and B∞ with the scene's ceiling fit where it has one "
        "(the best-fitting values of the formation model), else with the truth. J PSNR: the clean "
        "image over the object pixels (finite true range) and over their nearest third (per view); "
        "depth abs-rel: per view median and mean over the object pixels, averaged over views. "
        "Ceiling rows: the formation model inverted with the true range (Ĵ clipped to [0, 1] for the PSNR only).",
        "",
        "### Curves (every evaluation)",
        "",
    ]
    head2 = ["scene", "method", "iter", "train s"] + [title for key, title, _ in PLOTTED]
    lines.append("| " + " | ".join(head2) + " |")
    lines.append("|" + "---|" * len(head2))
    for run in results.get("runs", []):
        for record in run.get("evals", []):
            row = [run["scene"], f"`{run['method']}`", str(record["step"]), f"{record['train_time']:.0f}"]
            row += [_fmt(_value(record, key), "{:.3f}") for key, _, _ in PLOTTED]
            lines.append("| " + " | ".join(row) + " |")
    gaps = ceiling_gaps(results)
    if gaps:
        lines += ["", "### Gaps to the ceiling (final evaluation)", ""] + gaps
    veil = veil_lines(results)
    if veil:
        lines += ["", "### β_B and the veil (final evaluation)", "", "Signed errors against the reference; the last column is "
                  "`(B∞ / B∞_ref)^s − 1`, the β_B error the veil's own error accounts for at the fit's sensitivity `s`.", ""] + veil
    codes = [run.get("code") for run in results.get("runs", [])]
    if codes and all(codes):
        dirty = sorted({f for code in codes for f in code.get("dirty_files", [])})
        commits = sorted({code.get("commit", "?")[:10] for code in codes})
        lines += ["", f"Code: commit(s) {', '.join(commits)}" + (f"; **uncommitted changes in {', '.join(dirty)}**" if dirty else "; clean tree") + "."]
    else:
        lines += ["", "Code: commit not recorded for every run."]
    if results.get("failures"):
        lines += ["", "Failed runs:", ""] + [f"- {f}" for f in results["failures"]]
    return "\n".join(lines) + "\n"


def plot_scene(results: Dict[str, Any], scene: str, path: Path) -> Path:
    """One figure per scene: each error against training wall time, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    runs = [r for r in results.get("runs", []) if r["scene"] == scene]
    keys = [(k, t, log) for k, t, log in PLOTTED if any(math.isfinite(_value(e, k)) for r in runs for e in r["evals"])]
    cols = 3
    rows = max(1, math.ceil(len(keys) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
    xlabel = "training wall time (s)"  # also for an iteration budget: the curves compare methods by time
    for ax, (key, title, log) in zip(axes.flat, keys):
        for run in runs:
            xs = [e["train_time"] for e in run["evals"]]
            ys = [_value(e, key) for e in run["evals"]]
            pts = [(x, y) for x, y in zip(xs, ys) if math.isfinite(y) and x > 0]
            if not pts:
                continue
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", label=run["method"])
        ceiling = ((results.get("ceilings") or {}).get(scene) or {}).get("variants", {}).get("ceiling")
        if ceiling and key in CEILING_SCORES and _metric(ceiling["metrics"], key) is not None:
            ax.axhline(_metric(ceiling["metrics"], key), color="black", linestyle="--", linewidth=1, label="ceiling")
        ax.set_title(title, fontsize=10)
        ax.set_xscale("log")
        ticks = []
        for t in sorted({round(e["train_time"]) for r in runs for e in r["evals"] if e["train_time"] > 0}):
            if not ticks or t > 1.1 * ticks[-1]:  # runs evaluated at nearly the same time share a tick
                ticks.append(t)
        if ticks:  # label the evaluation times (a span inside one decade has no major log ticks)
            ax.set_xticks(ticks if len(ticks) <= 6 else ticks[:: math.ceil(len(ticks) / 6)])
            ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%d"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        values = [_value(e, key) for r in runs for e in r["evals"] if math.isfinite(_value(e, key))]
        if log and values and min(values) > 0 and max(values) > 10 * min(values):  # log only across decades
            ax.set_yscale("log")
        ax.set_xlabel(xlabel, fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
    for ax in list(axes.flat)[len(keys) :]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=min(4, len(labels)), fontsize=9)
    fig.suptitle(f"seathru-bench: {scene}", fontsize=12)
    fig.tight_layout(rect=(0, 0.06, 1, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def merge_results(parts: List[Dict[str, Any]]) -> Dict[str, Any]:
    """One results record from several runs of ``seathru-bench run`` (runs concatenated)."""
    merged = dict(parts[0])
    merged["runs"] = [run for part in parts for run in part.get("runs", [])]
    merged["failures"] = [f for part in parts for f in part.get("failures", [])]
    merged["ceilings"] = {k: v for part in parts for k, v in (part.get("ceilings") or {}).items()}
    merged["parts"] = [
        {k: part.get(k) for k in ("created", "command", "budget_kind", "budget", "machine")} for part in parts
    ]
    return merged


def write_report(results: Dict[str, Any], out: Path) -> Dict[str, Path]:
    """Write ``results.md`` and ``bench_<scene>.png`` into ``out``; returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    written = {"table": out / "results.md"}
    written["table"].write_text("# seathru-bench results\n\n" + markdown_table(results))
    for scene in dict.fromkeys(r["scene"] for r in results.get("runs", [])):
        safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in scene)
        written[f"plot:{scene}"] = plot_scene(results, scene, out / f"bench_{safe}.png")
    return written
