"""Which rays does the veil in front of the surfaces read? (About a minute of CPU per run on 2 cores; needs a run
saved with ``seathru-bench run --save-model`` or ``ns-train``, and the scene's ground truth.)

Renders the run's held-out views. Per channel, the rays the reader would count at the run's end
(:mod:`seathru_nerfstudio.surface_veil`: object opacity at least 0.95, rendered range times the run's
attenuation at least 3; every channel, though the reader skips one whose depth of 3 attenuation lengths lies
past the SfM far bound, which is printed with where the deep rays sit against it) are split by the truth: open
water (no surface on the ray) and surfaces. Printed per channel: how many of each, their median colour over the
veil the run renders them with, the surfaces' median true range, and the same median over the surfaces that are truly that deep (true range and ``β_D``), which is
what the reader should find.

    .venv/bin/python scripts/probe_surface_veil.py RUN/config.yml outputs/pathtraced/coastal_s3
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch


def main(config: Path, scene: Path) -> None:
    from held_out_views import held_out_renders, load_run

    from seathru_nerfstudio.surface_veil import SURFACE_ACCUMULATION

    pipeline, scale = load_run(config)
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    attenuation = torch.nn.functional.softplus(model.medium_field.density_raw.detach().double())[:3].numpy() * scale
    true_attenuation = np.asarray(json.loads((scene / "ground_truth" / "medium.json").read_text())["beta_D"], dtype=float)
    columns = {k: [] for k in ("range", "accumulation", "depth", "ratio")}
    for index, _, _, true_range, outputs in held_out_renders(pipeline, scene):
        observed = dataset.get_image_float32(index)[..., :3].numpy()
        columns["range"].append(true_range.reshape(-1))
        columns["accumulation"].append(outputs["accumulation"][..., 0].numpy().reshape(-1))
        columns["depth"].append(outputs["depth"][..., 0].numpy().reshape(-1) / scale)
        columns["ratio"].append((observed / outputs["medium_rgb"].numpy()).reshape(-1, 3))
    data = {k: np.concatenate(v) for k, v in columns.items()}
    surface = data["accumulation"] >= SURFACE_ACCUMULATION
    open_water = ~np.isfinite(data["range"])
    print(f"run attenuation {np.round(attenuation, 4)} /m, true {true_attenuation}; {surface.sum()} surface rays of {surface.size}")
    end = None if model.far_range is None else model.far_range * model.config.far_bound_margin
    if end is not None:
        print(f"SfM far bound {model.far_range:.2f} world units; the object field ends at {end:.2f}")
        for c, name in enumerate("rgb"):
            deep = surface & (data["depth"] * attenuation[c] >= 3.0)
            edges = np.quantile(data["depth"][deep] / end, [0.1, 0.25, 0.5, 0.75, 0.9]) if deep.any() else []
            print(f"  {name}: deep rays' rendered range over the field's end, 10/25/50/75/90%: {np.round(edges, 3)}")
    for c, name in enumerate("rgb"):
        deep = surface & (data["depth"] * attenuation[c] >= 3.0)
        truly_deep = np.isfinite(data["range"]) & (data["range"] * true_attenuation[c] >= 3.0)
        parts = []
        for label, keep in (("open water", deep & open_water), ("surfaces", deep & ~open_water), ("truly deep", truly_deep)):
            ratio = data["ratio"][keep, c]
            median = f"{np.median(ratio):.3f}" if ratio.size else "-"
            far = f", true range {np.median(data['range'][keep]):.1f} m" if label == "surfaces" and keep.any() else ""
            parts.append(f"{label} {int(keep.sum())} ({keep.sum() / max(surface.sum(), 1):.1%}) median {median}{far}")
        print(f"{name}: deep at 3 / {attenuation[c]:.3f} = {3.0 / attenuation[c]:.1f} m: " + "; ".join(parts))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: probe_surface_veil.py RUN/config.yml SCENE_DIR")
    sys.path.insert(0, str(Path(__file__).parent))
    main(Path(sys.argv[1]), Path(sys.argv[2]))
