"""nerfstudio's vanilla pipeline, with evaluation always on linear outputs.

Camera renders of a SeaThru model outside training are display renders
(:mod:`seathru_nerfstudio.viewer`: viewer overrides, exposure, sRGB), which is what the viewer
and ``ns-render`` need. Metrics must not see that: every evaluation entry point here runs
inside :func:`seathru_nerfstudio.viewer.linear_outputs`, so ``ns-eval`` and the evaluations
during ``ns-train`` measure the trained model's plain linear outputs, whatever the viewer's
controls are set to.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, Optional, Type

from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig

from seathru_nerfstudio import viewer


@dataclass
class SeathruPipelineConfig(VanillaPipelineConfig):
    """VanillaPipelineConfig whose evaluations use linear outputs."""

    _target: Type = field(default_factory=lambda: SeathruPipeline)


class SeathruPipeline(VanillaPipeline):
    """VanillaPipeline; evaluations on linear outputs, viewer controls in a ``seathru`` folder."""

    def __init__(
        self,
        config: SeathruPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: Optional[Any] = None,
    ):
        super().__init__(config, device, test_mode, world_size, local_rank, grad_scaler)
        controls = viewer.controls_of(self.model)
        if controls is not None:
            # The viewer lists elements under their shortest attribute path: this puts the
            # controls in "Custom Elements/seathru" rather than ".../model/viewer_controls".
            self.seathru = controls

    def get_eval_loss_dict(self, step: int):
        with viewer.linear_outputs():
            return super().get_eval_loss_dict(step)

    def get_eval_image_metrics_and_images(self, step: int):
        with viewer.linear_outputs():
            return super().get_eval_image_metrics_and_images(step)

    def get_average_image_metrics(self, *args, **kwargs):
        with viewer.linear_outputs():
            return super().get_average_image_metrics(*args, **kwargs)
