"""``seathru-bench render-cost``: what one camera render costs, by the outputs that are read.

The viewer reads the output chosen in its panel and ``depth``; ``ns-render`` reads its
``--rendered-output-names``. A SeathruModel computes an output only when it is read
(:mod:`seathru_nerfstudio.lazy_outputs`); this prints, for the usual requests, the seconds per
image and how often the object field's colour head and the medium were evaluated, against
reading every output (what an eager render computes for any request).

The costs do not depend on what the model has learned (fixed sample counts), so by default an
untrained ``seathru-nerf-lite`` model is measured; ``--load-config`` measures a trained run.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch

from nerfstudio.utils.rich_utils import CONSOLE

REQUESTS: Dict[str, Tuple[str, ...]] = {
    "every output (eager)": (),
    "viewer, water on: rgb_display + depth": ("rgb_display", "depth"),
    "viewer, water off: rgb_display + depth": ("rgb_display", "depth"),
    "ns-render clean": ("clean",),
    "ns-render depth": ("depth",),
    "viewer: medium_attenuation_display + depth": ("medium_attenuation_display", "depth"),
    "ns-render medium_attenuation": ("medium_attenuation",),
}
"""Named requests: the outputs read (empty: every output)."""


@dataclass
class RenderCostConfig:
    """Seconds per camera render and field/medium evaluations, by the outputs read."""

    load_config: Optional[Path] = None
    """A trained run's config.yml (as for ns-render); default: an untrained seathru-nerf-lite."""
    width: int = 160
    height: int = 120
    repeats: int = 3
    """Renders per request; the median time is printed."""
    medium_model: str = "seathru"
    """Medium model of the untrained model (ignored with --load-config)."""


def _untrained_model(config: RenderCostConfig):
    from nerfstudio.data.scene_box import SceneBox

    from seathru_nerfstudio.config import seathru_nerf_lite_config
    from seathru_nerfstudio.metrics import offline_lpips

    model_config = seathru_nerf_lite_config().pipeline.model
    model_config.medium_model = config.medium_model
    with offline_lpips():
        return model_config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]])), num_train_data=1)


def _camera(width: int, height: int):
    from nerfstudio.cameras.cameras import Cameras

    c2w = torch.eye(4)[:3][None]
    c2w[0, 2, 3] = 1.5  # outside the unit box, looking along -z into it
    focal = 0.8 * width
    return Cameras(camera_to_worlds=c2w, fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height)


def measure(model, camera, repeats: int) -> List[dict]:
    """One row per request of :data:`REQUESTS`: median seconds, colour-head and medium calls per render."""
    counts = {"field": 0, "medium": 0}
    hooks = [
        model.field.mlp_head.register_forward_hook(lambda *_: counts.__setitem__("field", counts["field"] + 1)),
        model.medium_field.register_forward_hook(lambda *_: counts.__setitem__("medium", counts["medium"] + 1)),
    ]
    rows = []
    try:
        for label, names in REQUESTS.items():
            model.viewer_controls.c1_water.value = "water off" not in label
            seconds = []
            for _ in range(repeats):
                counts.update(field=0, medium=0)
                start = time.perf_counter()
                outputs = model.get_outputs_for_camera(camera)
                for name in names or list(outputs):
                    outputs[name]
                seconds.append(time.perf_counter() - start)
            rows.append(dict(request=label, seconds=statistics.median(seconds), **counts))
    finally:
        model.viewer_controls.c1_water.value = True
        for hook in hooks:
            hook.remove()
    return rows


def run_render_cost(config: RenderCostConfig) -> List[dict]:
    if config.load_config is not None:
        from nerfstudio.utils.eval_utils import eval_setup

        _, pipeline, _, _ = eval_setup(config.load_config, test_mode="inference")
        model = pipeline.model
    else:
        model = _untrained_model(config)
    model.eval()
    torch.manual_seed(0)
    rows = measure(model, _camera(config.width, config.height), config.repeats)
    eager = rows[0]["seconds"]
    load = Path("/proc/loadavg").read_text().split()[:3] if Path("/proc/loadavg").exists() else ["?"] * 3
    CONSOLE.print(
        f"render cost, {config.width}x{config.height}, medium model {model.medium_model}, "
        f"{torch.get_num_threads()} threads, load average {' '.join(load)}"
    )
    CONSOLE.print(f"{'request':46s} {'s/image':>8s} {'vs eager':>8s} {'field':>6s} {'medium':>6s}")
    for row in rows:
        CONSOLE.print(
            f"{row['request']:46s} {row['seconds']:8.3f} {row['seconds'] / eager:8.2f} {row['field']:6d} {row['medium']:6d}"
        )
    return rows
