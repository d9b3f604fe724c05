"""A kept run's renders of its held-out views, beside the scene's true range: what the offline
probes (``probe_open_water.py``, ``probe_depth_error.py``) read. Imported by them, not run."""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Tuple

import numpy as np
import torch


def load_run(config: Path) -> Tuple[object, float]:
    """The run's pipeline, loaded for evaluation (nerfacto's runs too, offline: its LPIPS is built by
    :func:`seathru_nerfstudio.metrics.offline_lpips`), and its scene units per world unit."""
    from nerfstudio.utils.eval_utils import eval_setup

    from seathru_nerfstudio.metrics import offline_lpips

    with offline_lpips():
        _, pipeline, _, _ = eval_setup(config, test_mode="test")
    return pipeline, float(pipeline.datamanager.eval_dataset._dataparser_outputs.dataparser_scale)


def held_out_renders(pipeline, scene: Path) -> Iterator[Tuple[int, str, object, np.ndarray, dict]]:
    """Per held-out view: its index in the eval dataset, its name, its camera, the true range
    (``ground_truth/depth/<name>.npy``: world units, ``inf`` on open water) and the model's render."""
    dataset = pipeline.datamanager.eval_dataset
    for index in range(len(dataset)):
        name = Path(dataset.image_filenames[index]).stem
        true_range = np.load(scene / "ground_truth" / "depth" / f"{name}.npy")
        camera = dataset.cameras[index : index + 1]
        with torch.no_grad():
            outputs = pipeline.model.get_outputs_for_camera(camera)
        yield index, name, camera, true_range, outputs
