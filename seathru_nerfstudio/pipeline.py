"""nerfstudio's vanilla pipeline whose evaluations measure the trained medium.

The viewer's water controls (density scale, veiling light) change the medium of every render
outside training (:mod:`seathru_nerfstudio.viewer`). While this pipeline evaluates (``ns-eval``,
the evaluations during ``ns-train``) it switches them off with the model's plain flag
``medium_controls_enabled``; nerfstudio's ``train_lock`` keeps the viewer's renders out of that
time. Metrics read the linear outputs (``rgb``, ``clean``, ...), never the display ones.

Also the class that saved configs (``config.yml``) name, and the base of the multi-process
pipeline in :mod:`seathru_nerfstudio.distributed`. It is the first code of ours that nerfstudio's
``ns-eval``, ``ns-render`` and ``ns-viewer`` run: bad input met while it is built (the dataparser's
checks, the model's) ends them with one line and exit status 1
(:func:`~seathru_nerfstudio.input_errors.exit_on_input_error`).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Iterator, Literal, Optional, Type

from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig

from seathru_nerfstudio.input_errors import exit_on_input_error
from seathru_nerfstudio.model import SeathruModel


@dataclass
class SeathruPipelineConfig(VanillaPipelineConfig):
    """VanillaPipelineConfig whose evaluations ignore the viewer's water controls."""

    _target: Type = field(default_factory=lambda: SeathruPipeline)


class SeathruPipeline(VanillaPipeline):
    """VanillaPipeline; evaluations without the viewer's water controls, which it shows in a
    ``seathru`` folder."""

    def __init__(
        self,
        config: SeathruPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: Optional[Any] = None,
    ):
        with exit_on_input_error():
            super().__init__(config, device, test_mode, world_size, local_rank, grad_scaler)
        if not isinstance(self.model, SeathruModel):
            raise TypeError(
                f"SeathruPipeline is for SeaThru models, not {type(self.model).__name__}: "
                "use nerfstudio's VanillaPipelineConfig for other models"
            )
        # The viewer lists elements under their shortest attribute path: this puts the controls
        # in "Custom Elements/seathru" rather than ".../model/viewer_controls".
        self.seathru = self.model.viewer_controls

    @contextmanager
    def trained_medium(self) -> Iterator[None]:
        """Within this block, renders use the trained medium, whatever the viewer's controls say."""
        model = self.model
        previous = model.medium_controls_enabled
        model.medium_controls_enabled = False
        try:
            yield
        finally:
            model.medium_controls_enabled = previous

    def get_eval_loss_dict(self, step: int):
        with self.trained_medium():
            return super().get_eval_loss_dict(step)

    def get_eval_image_metrics_and_images(self, step: int):
        with self.trained_medium():
            return super().get_eval_image_metrics_and_images(step)

    def get_average_image_metrics(self, *args, **kwargs):
        with self.trained_medium():
            return super().get_average_image_metrics(*args, **kwargs)
