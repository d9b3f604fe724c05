"""``seathru-bench numerics``: the renderer's quadratures against dense references.

Each *profile* is one ray with an analytic object density ``sigma(t)`` and colour ``c(t)`` in a
homogeneous medium (``sigma_attn``, ``sigma_bs``, ``c_med`` per channel). The ray is cut into
``N`` equal intervals between the near and far planes (as nerfstudio's samplers do, but not
aligned with the object's edges) and rendered with :func:`render_seathru` under four
*schemes*: quadrature ``analytic`` or ``paper``, with the field sampled at each interval's
midpoint (what nerfstudio does: ``frustums.get_positions()``) or at its left end.

References: profiles made of constant slabs have a closed form, integrated here
independently of the renderer, slab by slab (:func:`exact_slabs`); smooth profiles use the
``analytic`` midpoint scheme at ``2^20`` intervals (checked against the slab integrator on a
staircase of the same profile). Errors are ``max |rgb - ref|`` over channels, float64, so the
convergence is not hidden by float32's 1e-7 floor; timings are float32 batches of rays.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from seathru_nerfstudio.rendering import render_seathru

SCHEMES: Tuple[Tuple[str, str, str], ...] = (
    ("analytic/mid", "analytic", "mid"),
    ("paper/mid", "paper", "mid"),
    ("analytic/left", "analytic", "left"),
    ("paper/left", "paper", "left"),
)


@dataclass
class Profile:
    """One analytic ray. Densities per scene unit; ``slabs`` are ``(start, end, density, rgb)``
    (``end`` may be ``inf``); ``smooth`` adds a density/colour function on top (no slabs then)."""

    name: str
    description: str
    sigma_attn: Tuple[float, float, float]
    sigma_bs: Tuple[float, float, float]
    c_med: Tuple[float, float, float]
    near: float = 0.05
    far: float = 6.0
    slabs: Tuple[Tuple[float, float, float, Tuple[float, float, float]], ...] = ()
    smooth: Optional[Tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray]]] = None
    jitter: bool = True
    """Average the error over edge phases: the slabs are shifted by ``(k + 1/2) / K`` of an
    interval, ``k < K``, so an edge's luck in falling on a sample boundary does not show as
    a convergence order. Off where the edge's place is the point (behind-near)."""

    def shifted(self, shift: float) -> "Profile":
        slabs = tuple((a + shift, b + shift, d, c) for a, b, d, c in self.slabs)
        return dataclasses.replace(self, slabs=slabs)

    def field(self, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Density ``[n]`` and colour ``[n, 3]`` at distances ``t``."""
        sigma = np.zeros_like(t)
        rgb = np.zeros(t.shape + (3,))
        for a, b, d, c in self.slabs:
            inside = (t >= a) & (t < b)
            sigma = np.where(inside, d, sigma)
            rgb = np.where(inside[:, None], np.asarray(c)[None, :], rgb)
        if self.smooth is not None:
            density_fn, colour_fn = self.smooth
            sigma = sigma + density_fn(t)
            rgb = colour_fn(t)  # a smooth profile has no slabs: its colour is the function's
        return sigma, rgb


WATER = dict(sigma_attn=(0.4, 0.3, 0.2), sigma_bs=(0.3, 0.25, 0.2), c_med=(0.07, 0.2, 0.39))
OBJ = (0.8, 0.5, 0.3)


def default_profiles() -> List[Profile]:
    return [
        Profile("wall", "opaque wall (sigma=50/u) at t=2 in water", slabs=((2.0, math.inf, 50.0, OBJ),), **WATER),
        Profile(
            "thin-dense",
            "thin very dense sheet (0.01 u, sigma=5000/u) at t=1.5 in thin medium (sigma=0.01/u)",
            sigma_attn=(0.01, 0.01, 0.01),
            sigma_bs=(0.01, 0.01, 0.01),
            c_med=(0.5, 0.5, 0.5),
            slabs=((1.5, 1.51, 5000.0, OBJ),),
        ),
        Profile("open-water", "no object: medium from the camera to infinity", **WATER),
        Profile(
            "behind-near",
            "dense object (sigma=200/u) starting 0.001 u behind the near plane (0.05)",
            slabs=((0.051, 1.0, 200.0, OBJ),),
            jitter=False,
            **WATER,
        ),
        Profile(
            "very-clear",
            "very clear water (sigma=1e-4/u), wall at t=3",
            sigma_attn=(1e-4, 1e-4, 1e-4),
            sigma_bs=(1e-4, 1e-4, 1e-4),
            c_med=(0.07, 0.2, 0.39),
            slabs=((3.0, math.inf, 50.0, OBJ),),
        ),
        Profile(
            "very-turbid",
            "very turbid water (sigma_attn=(8,6,5)/u), wall at t=1",
            sigma_attn=(8.0, 6.0, 5.0),
            sigma_bs=(6.0, 5.0, 4.0),
            c_med=(0.07, 0.2, 0.39),
            slabs=((1.0, math.inf, 50.0, OBJ),),
        ),
        Profile(
            "smooth-blob",
            "smooth Gaussian density bump (peak 20/u at t=2, width 0.3) with smoothly varying colour",
            smooth=(
                lambda t: 20.0 * np.exp(-0.5 * ((t - 2.0) / 0.3) ** 2),
                lambda t: np.stack([0.5 + 0.3 * np.sin(t), 0.4 + 0.2 * np.cos(2 * t), 0.3 + 0.1 * t / 6], -1),
            ),
            jitter=False,
            **WATER,
        ),
    ]


def exact_slabs(profile: Profile) -> np.ndarray:
    """Closed-form ``rgb`` of a profile made of constant slabs (float64, independent of
    :mod:`seathru_nerfstudio.rendering`): integrate each constant piece of
    ``T_obj(t) e^{-sigma_m t} (sigma_obj c + sigma_bs c_med)`` exactly, camera to infinity."""
    assert profile.smooth is None
    attn, bs, cmed = (np.asarray(x, dtype=np.float64) for x in (profile.sigma_attn, profile.sigma_bs, profile.c_med))
    cuts = sorted({0.0, math.inf, *[a for a, _, _, _ in profile.slabs], *[b for _, b, _, _ in profile.slabs]})
    rgb = np.zeros(3)
    tau = 0.0  # object optical depth at the start of the piece
    for a, b in zip(cuts[:-1], cuts[1:]):
        mid = a + 1.0 if math.isinf(b) else 0.5 * (a + b)
        sigma, colour = profile.field(np.array([mid]))
        d, c = float(sigma[0]), colour[0]
        length = b - a
        for k, medium, source in ((0, attn, d * c), (1, bs, bs * cmed)):
            total = d + medium
            # int_a^b e^{-tau - d (t-a) - medium t} dt * source
            with np.errstate(over="ignore", invalid="ignore"):
                start = np.exp(-tau - medium * a)
                frac = np.where(total > 0, -np.expm1(-total * length) / np.where(total > 0, total, 1.0), length)
            rgb = rgb + np.where(np.isfinite(frac), start * frac * source, 0.0)
        tau += d * length if d > 0 else 0.0
        if math.isinf(tau):
            break
    return rgb


def render_profile(
    profile: Profile, n: int, quadrature: str, sample_at: str, dtype=torch.float64, rays: int = 1
) -> Tuple[torch.Tensor, Dict]:
    """Render ``rays`` copies of the profile with ``n`` equal intervals in ``[near, far]``."""
    edges = np.linspace(profile.near, profile.far, n + 1)
    starts, deltas = edges[:-1], np.diff(edges)
    points = starts + 0.5 * deltas if sample_at == "mid" else starts
    sigma, colour = profile.field(points)

    def t(x: np.ndarray, shape) -> torch.Tensor:
        return torch.as_tensor(x, dtype=dtype).reshape(shape).expand(rays, *shape).contiguous()

    kwargs = dict(
        object_rgb=t(colour, (n, 3)),
        object_density=t(sigma, (n, 1)),
        starts=t(starts, (n, 1)),
        deltas=t(deltas, (n, 1)),
        medium_rgb=t(np.asarray(profile.c_med), (3,)),
        sigma_attn=t(np.asarray(profile.sigma_attn), (3,)),
        sigma_bs=t(np.asarray(profile.sigma_bs), (3,)),
        quadrature=quadrature,
    )
    return render_seathru(**kwargs).rgb, kwargs


def reference(profile: Profile, dense: int = 1 << 20) -> np.ndarray:
    if profile.smooth is None:
        return exact_slabs(profile)
    rgb, _ = render_profile(profile, dense, "analytic", "mid")
    return rgb[0].numpy()


def observed_order(ns: Sequence[int], errors: Sequence[float], floor: float = 1e-10) -> float:
    """Least-squares slope of ``-log(err)`` against ``log(N)`` over the points above ``floor``
    (float64 round-off of an N-term sum reaches ~1e-12 at N = 2^14, so 1e-10 means exact);
    ``inf`` when every error is at the floor (exact)."""
    pts = [(math.log(n), math.log(e)) for n, e in zip(ns, errors) if e > floor]
    if len(pts) < 2:
        return math.inf
    x, y = np.array(pts).T
    return float(-np.polyfit(x, y, 1)[0])


@dataclass
class NumericsConfig:
    """Error of the renderer's quadratures against dense references, vs sample count and time."""

    output_dir: Path = Path("outputs/bench")
    """Where numerics.json, numerics.md and bench_numerics_*.png go."""
    min_log2_samples: int = 2
    """Smallest sample count, as a power of 2."""
    max_log2_samples: int = 14
    """Largest sample count, as a power of 2."""
    timing_rays: int = 1024
    """Rays per timed float32 render (one training batch of seathru-nerf-lite)."""
    timing_max_log2_samples: int = 10
    """Largest timed sample count (1024 rays x 2^10 samples is ~12 MB a tensor)."""
    timing_repeats: int = 5
    """Best of this many timed renders (CPU time of one thread)."""
    phases: int = 8
    """Edge phases averaged (RMS) for slab profiles (see ``Profile.jitter``)."""
    profiles: Tuple[str, ...] = ()
    """Subset of profiles to run (default: all)."""
    plot: bool = True


def run_numerics(config: NumericsConfig) -> Dict:
    out = config.output_dir
    out.mkdir(parents=True, exist_ok=True)
    profiles = [p for p in default_profiles() if not config.profiles or p.name in config.profiles]
    ns = [2**k for k in range(config.min_log2_samples, config.max_log2_samples + 1)]
    timed = [n for n in ns if n <= 2**config.timing_max_log2_samples]

    # CPU time of one thread, best of several: on a shared machine wall time measures the
    # neighbours more than the renderer.
    timing: Dict[str, List[float]] = {}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            for label, quadrature, sample_at in SCHEMES:
                timing[label] = []
                for n in timed:
                    _, kwargs = render_profile(profiles[0], n, quadrature, sample_at, torch.float32, config.timing_rays)
                    render_seathru(**kwargs)  # warm-up
                    best = math.inf
                    for _ in range(config.timing_repeats):
                        t0 = time.process_time()
                        render_seathru(**kwargs)
                        best = min(best, time.process_time() - t0)
                    timing[label].append(best)
    finally:
        torch.set_num_threads(threads)
    with torch.no_grad():

        records = []
        for profile in profiles:
            phases = config.phases if profile.jitter and profile.smooth is None else 1
            ref = reference(profile)
            entry = {
                "profile": profile.name,
                "description": profile.description,
                "reference": ref.tolist(),
                "reference_kind": "closed form (slabs)" if profile.smooth is None else "analytic/mid at 2^20",
                "phases": phases,
                "schemes": {},
            }
            for label, quadrature, sample_at in SCHEMES:
                errors = []
                for n in ns:
                    delta = (profile.far - profile.near) / n
                    squared = []
                    for k in range(phases):
                        shifted = profile.shifted((k + 0.5) / phases * delta) if phases > 1 else profile
                        ref_k = exact_slabs(shifted) if phases > 1 else ref
                        rgb, _ = render_profile(shifted, n, quadrature, sample_at)
                        squared.append(float(np.max(np.abs(rgb[0].numpy() - ref_k))) ** 2)
                    errors.append(math.sqrt(sum(squared) / len(squared)))  # RMS over edge phases
                entry["schemes"][label] = {"errors": errors, "order": observed_order(ns, errors)}
            records.append(entry)

    results = {"samples": ns, "timing_samples": timed, "timing_rays": config.timing_rays, "timing_seconds": timing, "profiles": records}
    (out / "numerics.json").write_text(json.dumps(results, indent=1, default=float))
    (out / "numerics.md").write_text(numerics_table(results))
    if config.plot:
        plot_numerics(results, out)
    print((out / "numerics.md").read_text())
    return results


def _e(x: float) -> str:
    return "0" if x == 0 else f"{x:.1e}"


def numerics_table(results: Dict) -> str:
    ns = results["samples"]
    shown = [n for n in (8, 32, 128, 1024, 16384) if n in ns]
    timed = results["timing_samples"]
    lines = [
        "| profile | scheme | " + " | ".join(f"err N={n}" for n in shown) + " | observed order |",
        "|---|---|" + "---|" * (len(shown) + 1),
    ]
    for entry in results["profiles"]:
        for label, data in entry["schemes"].items():
            errs = [data["errors"][ns.index(n)] for n in shown]
            order = data["order"]
            order_text = "exact" if math.isinf(order) else f"{order:.2f}"
            lines.append(f"| {entry['profile']} | {label} | " + " | ".join(_e(e) for e in errs) + f" | {order_text} |")
    lines += [
        "",
        "Errors: max over RGB of |rgb - reference| (float64), RMS over edge phases for "
        "slab profiles. Observed order: slope of -log(error) against log(N) over all N with "
        "error > 1e-10 (`exact`: every error below that, i.e. round-off).",
        "",
        f"CPU time of one float32 render of {results['timing_rays']} rays on one thread (best of several), ms:",
        "",
        "| scheme | " + " | ".join(f"N={n}" for n in shown if n in timed) + " |",
        "|---|" + "---|" * len([n for n in shown if n in timed]),
    ]
    for label, secs in results["timing_seconds"].items():
        lines.append(f"| {label} | " + " | ".join(f"{1000 * secs[timed.index(n)]:.2f}" for n in shown if n in timed) + " |")
    lines += ["", "Profiles:", ""] + [f"- **{e['profile']}**: {e['description']}" for e in results["profiles"]]
    return "\n".join(lines) + "\n"


def plot_numerics(results: Dict, out: Path) -> List[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ns = results["samples"]
    paths = []
    for kind in ("samples", "time"):
        profiles = results["profiles"]
        cols = 4
        rows = math.ceil(len(profiles) / cols)
        fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.1 * rows), squeeze=False)
        for ax, entry in zip(axes.flat, profiles):
            for label, data in entry["schemes"].items():
                if kind == "samples":
                    xs, ys = ns, [max(e, 1e-17) for e in data["errors"]]
                else:
                    timed = results["timing_samples"]
                    xs = [1000 * s for s in results["timing_seconds"][label]]
                    ys = [max(data["errors"][ns.index(n)], 1e-17) for n in timed]
                order = data["order"]
                tag = "exact" if math.isinf(order) else f"p={order:.2f}"
                ax.loglog(xs, ys, marker=".", label=f"{label} ({tag})")
            ax.set_title(entry["profile"], fontsize=10)
            ax.set_xlabel("samples per ray" if kind == "samples" else f"CPU ms per {results['timing_rays']} rays (float32, 1 thread)", fontsize=8)
            ax.set_ylabel("max |rgb - ref|", fontsize=8)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=6)
        for ax in list(axes.flat)[len(profiles) :]:
            ax.axis("off")
        fig.suptitle("renderer quadratures: error vs " + ("samples" if kind == "samples" else "time"), fontsize=12)
        fig.tight_layout(rect=(0, 0, 1, 0.95))
        path = out / f"bench_numerics_{kind}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths
