"""Where does a trained run fill the open water? (About a minute of CPU per run on 2 cores; needs a run saved with
``seathru-bench run --save-model`` or ``ns-train``, and the scene's ground truth.)

Renders the run's held-out views and keeps the open-water pixels (``ground_truth/depth`` is
``inf`` there: no surface on the ray). Printed:

* per view, the share of those pixels whose object opacity (``accumulation``) is above 0.5, the
  opacity above which ``ns-export pointcloud`` keeps a point (``export.OPACITY_THRESHOLD``);
* by quintile of the ray's ``sin(elevation)`` along the run's own scene vertical: the mean
  opacity, the share above 0.5, the mean ``clean`` colour (what the water-free image shows there,
  where the truth is black), the true colour in the medium, the render's mean error against it
  (linear), and the median ``depth`` in world units (metres on ``seathru-pathtrace`` scenes).

It says whether the object field fills open water that is darker than the veil it holds (a
render error near 0 beside an opacity near 1 at low elevations) or brighter.

    .venv/bin/python scripts/probe_open_water.py RUN/config.yml outputs/pathtraced/coastal_s3
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

NUM_BANDS = 5


def open_water_samples(config: Path, scene: Path):
    """Per open-water pixel of every held-out view: ``up`` (sin of the elevation), ``accumulation``,
    ``clean`` (3), the render ``rgb`` (3), the true colour (3) and ``depth`` (world units)."""
    from held_out_views import held_out_renders, load_run

    from seathru_nerfstudio.export import OPACITY_THRESHOLD
    from seathru_nerfstudio.medium_field import sin_elevation

    pipeline, scale = load_run(config)
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    medium = model.medium_field
    if hasattr(medium, "veil_rise"):
        print(
            f"held veil {[round(float(v), 4) for v in torch.sigmoid(medium.rgb_logit)]}, rising by "
            f"{[round(float(v), 3) for v in medium.veil_rise]} per unit of sin(elevation) from "
            f"{[round(float(v), 3) for v in medium.veil_rise_from]} to {float(medium.veil_rise_to):+.3f}"
        )
    columns = {k: [] for k in ("up", "accumulation", "clean", "rgb", "truth", "depth")}
    for index, name, camera, true_range, outputs in held_out_renders(pipeline, scene):
        open_water = ~np.isfinite(true_range)
        with torch.no_grad():
            directions = camera.generate_rays(camera_indices=0).directions
            up = sin_elevation(directions, model.medium_field.vertical)[..., 0]
        values = {
            "up": up.numpy(),
            "accumulation": outputs["accumulation"][..., 0].numpy(),
            "clean": outputs["clean"].numpy(),
            "rgb": outputs["rgb"].numpy(),
            "truth": dataset.get_image_float32(index)[..., :3].numpy(),
            "depth": outputs["depth"][..., 0].numpy() / scale,
        }
        for key, value in values.items():
            columns[key].append(value[open_water])
        share = float(np.mean(values["accumulation"][open_water] > OPACITY_THRESHOLD)) if open_water.any() else float("nan")
        print(f"{name}: {int(open_water.sum())} open-water pixels, {share:.2f} of them above opacity {OPACITY_THRESHOLD}")
    return {key: np.concatenate(parts) for key, parts in columns.items()}


def main(config: Path, scene: Path) -> None:
    samples = open_water_samples(config, scene)
    if samples["up"].size == 0:
        sys.exit(f"{scene}: the held-out views show no open water (ground_truth/depth is finite everywhere)")
    edges = np.quantile(samples["up"], np.linspace(0.0, 1.0, NUM_BANDS + 1))
    show = lambda values: "(" + ", ".join(f"{v:.3f}" for v in values) + ")"  # noqa: E731
    for low, high in zip(edges[:-1], edges[1:]):
        band = (samples["up"] >= low) & (samples["up"] <= high)
        print(
            f"sin(elevation) {low:+.2f}..{high:+.2f}: {int(band.sum())} px, opacity {samples['accumulation'][band].mean():.2f} "
            f"(above 0.5: {np.mean(samples['accumulation'][band] > 0.5):.2f}), clean {show(samples['clean'][band].mean(0))}, "
            f"true {show(samples['truth'][band].mean(0))}, render - true {show((samples['rgb'][band] - samples['truth'][band]).mean(0))}, "
            f"depth median {np.median(samples['depth'][band]):.1f}"
        )


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: probe_open_water.py RUN/config.yml SCENE_FOLDER")
    main(Path(sys.argv[1]), Path(sys.argv[2]))
