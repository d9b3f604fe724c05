"""Which loss term spikes? (A few minutes of CPU on 2 cores; needs a run saved with
``seathru-bench run --save-model`` or ``ns-train``.)

Loads a checkpoint, then draws ``BATCHES`` training batches as training does and prints, for each
term of the loss, its median and its largest values over the batches, and for the batch with the
largest total the rays that carry it: the term's per-ray share, the predicted and the observed
colour.

    .venv/bin/python scripts/probe_loss_spikes.py RUN/config.yml STEP [BATCHES]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch


def per_ray_rgb_terms(outputs, batch, eps: float) -> torch.Tensor:
    """``(N,)`` each ray's share of the RawNeRF loss (the mean over rays and channels)."""
    image = batch["image"][..., :3]
    pred = outputs["rgb"]
    scale = pred.clamp_min(0.0) + eps
    return (((pred - image) / scale) ** 2).sum(-1) / pred.numel()


def per_ray_depth_terms(model, outputs, batch):
    """``(K, 4)`` for each ray with a known SfM depth: its DS-NeRF loss (unweighted, as nerfstudio sums it),
    the known range, the expected range and the largest object weight within the kernel."""
    from seathru_nerfstudio.losses import depth_kernel_variance

    known = batch["depth_image"].to(outputs["expected_depth"].device)
    hit = (known > 0)[..., 0]
    samples = outputs["ray_samples_list"][-1]
    weights = outputs["weights_list"][-1]
    norm = outputs.get("directions_norm", torch.ones_like(known))
    target = (known * norm)[hit]
    starts, ends = samples.frustums.starts[hit], samples.frustums.ends[hit]
    variance = depth_kernel_variance(starts, ends, target, model.config.research.depth_sigma * model.world_scale)
    mid = 0.5 * (starts + ends)
    kernel = torch.exp(-((mid - target[..., None, :]) ** 2) / (2 * variance))
    loss = (-torch.log(weights[hit] + 1e-7) * kernel * (ends - starts)).sum(-2)[..., 0]
    near = (weights[hit] * (kernel > 0.5)).amax(-2)[..., 0]
    expected = (outputs["expected_depth"] * norm)[hit][..., 0]
    return torch.stack([loss, target[..., 0], expected, near], -1)


def main(config: Path, step: int, batches: int) -> None:
    from nerfstudio.utils.eval_utils import eval_setup

    def load_step(cfg):
        cfg.load_step = step
        return cfg

    _, pipeline, _, _ = eval_setup(config, test_mode="val", update_config_callback=load_step)
    model, datamanager = pipeline.model, pipeline.datamanager
    model.train()
    model.train_step = step
    eps = model.config.research.rawnerf_eps
    records, worst = [], None
    max_ray = [-1.0]
    torch.manual_seed(0)
    for index in range(batches):
        ray_bundle, batch = datamanager.next_train(step)
        with torch.no_grad():
            outputs = model(ray_bundle)
            metrics = model.get_metrics_dict(outputs, batch)
            losses = {name: float(value) for name, value in model.get_loss_dict(outputs, batch, metrics).items()}
            depth_rays = per_ray_depth_terms(model, outputs, batch)
        losses["total"] = sum(losses.values())
        losses["known_rays"] = float(depth_rays.shape[0])
        if depth_rays.shape[0]:
            worst_ray = depth_rays[torch.argmax(depth_rays[:, 0])].tolist()
            if worst_ray[0] > max_ray[0]:
                max_ray = worst_ray
        records.append(losses)
        if worst is None or losses["total"] > worst[0]["total"]:
            rays = per_ray_rgb_terms(outputs, batch, eps)
            top = torch.argsort(rays, descending=True)[:5]
            worst = (
                losses,
                [(float(rays[i]), outputs["rgb"][i].tolist(), batch["image"][i, :3].tolist()) for i in top.tolist()],
            )
    print(f"{config} at step {step}, {batches} batches:")
    for name in records[0]:
        values = np.array([record.get(name, 0.0) for record in records])
        top = np.sort(values)[-3:][::-1]
        print(f"  {name}: median {np.median(values):.4g}, largest {', '.join(f'{v:.4g}' for v in top)}")
    print(f"  the worst known-depth ray: DS-NeRF loss {max_ray[0]:.4g}, SfM range {max_ray[1]:.4g}, expected {max_ray[2]:.4g}, "
          f"largest weight within the kernel {max_ray[3]:.3g}")
    print(f"  the largest total: {worst[0]}")
    for share, pred, observed in worst[1]:
        print(f"    ray: RawNeRF share {share:.4g}, predicted {np.round(pred, 4)}, observed {np.round(observed, 4)}")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit("usage: probe_loss_spikes.py RUN/config.yml STEP [BATCHES]")
    main(Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) > 3 else 200)
