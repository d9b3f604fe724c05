"""The registered methods: ``seathru-nerf`` (GPU, paper-faithful) and ``seathru-nerf-lite`` (CPU/laptop).

Both are built by :func:`method_config`; they differ only in size (rays, samples, hash grid,
medium MLP), iterations and evaluation cadence.
"""

from __future__ import annotations

from typing import Any, Dict

import torch

from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.parallel_datamanager import ParallelDataManagerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.plugins.types import MethodSpecification

from seathru_nerfstudio import compat
from seathru_nerfstudio.data.datamanager import SeathruDataManager  # its worker follows the trainer, its death ends the run
from seathru_nerfstudio.data.nerfstudio_data import SeathruNerfstudioDataParserConfig
from seathru_nerfstudio.data.seeded_sampler import SeededPixelSamplerConfig  # repeatable runs
from seathru_nerfstudio.model_config import SeathruModelConfig
from seathru_nerfstudio.pipeline import SeathruPipelineConfig  # evaluations without the viewer's water controls
from seathru_nerfstudio.training import SeathruTrainerConfig  # non-finite guard, crash-safe checkpoints

compat.allow_nerfstudio_checkpoints()

LOOPBACK = "127.0.0.1"
"""Our viewer listens on loopback only; ``--viewer.websocket-host 0.0.0.0`` opts in to more."""

MEDIUM_FIRST_STEPS = 200
"""Steps in which only the veiling light learns (``SeathruModelConfig.medium_first_steps``)."""


def _machine() -> MachineConfig:
    """CUDA when there is a GPU, else the CPU (nerfstudio's default would crash without one)."""
    if torch.cuda.is_available():
        return MachineConfig(device_type="cuda")
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        return MachineConfig(device_type="mps")
    return MachineConfig(device_type="cpu")


def _optimizers(max_steps: int) -> dict:
    adam = lambda: {  # noqa: E731
        "optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15),
        "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_steps),
    }
    return {
        "proposal_networks": adam(),
        "fields": adam(),
        # The veiling light is seen directly in open water: fast, so that it settles before the
        # object field starts and stays there (slow, the object field fills the open water to
        # correct it: measured opacity 0.7 there).
        "medium": {
            "optimizer": AdamOptimizerConfig(lr=5e-2, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=5e-4, max_steps=max_steps),
        },
        # The densities are only weakly determined by the images: slower than the veiling light, or
        # they absorb the young object field's errors (measured: green beta_D 1.9 -> 8.6 /m within
        # 150 steps of the object starting at 5e-2). A ramp 1e-3 -> 5e-2 over 400 steps found the
        # attenuation in one run and ran away (beta_D 2.0 /m, clean 5.4 dB) in another: not the
        # default (d826fe6, 2026-11-24; docs/history.md).
        "medium_density": adam(),
        "camera_opt": {
            "optimizer": AdamOptimizerConfig(lr=1e-3, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=5000),
        },
    }


def method_config(
    method_name: str,
    *,
    iterations: int,
    rays: int,
    chunk: int,
    optimizer_steps: int,
    model: Dict[str, Any],
    **trainer: Any,
) -> TrainerConfig:
    """One SeaThru method: ``rays`` per batch, renders in chunks of ``chunk`` rays,
    ``model`` on top of :class:`SeathruModelConfig`'s defaults, ``trainer`` on top of
    :class:`SeathruTrainerConfig`'s."""
    return SeathruTrainerConfig(
        method_name=method_name,
        max_num_iterations=iterations,
        machine=_machine(),
        pipeline=SeathruPipelineConfig(
            datamanager=ParallelDataManagerConfig(
                _target=SeathruDataManager,
                dataparser=SeathruNerfstudioDataParserConfig(),
                train_num_rays_per_batch=rays,
                eval_num_rays_per_batch=rays,
                pixel_sampler=SeededPixelSamplerConfig(),
            ),
            model=SeathruModelConfig(
                eval_num_rays_per_chunk=chunk,
                average_init_density=0.01,
                medium_first_steps=MEDIUM_FIRST_STEPS,
                **model,
            ),
        ),
        optimizers=_optimizers(optimizer_steps),
        viewer=ViewerConfig(num_rays_per_chunk=chunk, websocket_host=LOOPBACK),
        vis="viewer",
        **trainer,
    )


def seathru_nerf_config() -> TrainerConfig:
    """Paper-faithful settings for a CUDA GPU: 16384 rays, the paper's 6x256 medium MLP."""
    return method_config(
        "seathru-nerf",
        iterations=50_000,
        rays=16384,
        chunk=1 << 15,
        optimizer_steps=200_000,
        model=dict(medium_num_layers=6, medium_hidden_dim=256),
        steps_per_eval_batch=500,
        steps_per_save=2000,
        mixed_precision=True,
    )


def seathru_nerf_lite_config() -> TrainerConfig:
    """Sized for a CPU or laptop GPU: 1024 rays, 64/32 proposal and 32 NeRF samples,
    a 2^15-entry 8-level hash grid, torch implementation, a 2x64 medium MLP."""
    iterations = 1500
    return method_config(
        "seathru-nerf-lite",
        iterations=iterations,
        rays=1024,
        chunk=1 << 13,
        optimizer_steps=iterations * 4,
        model=dict(
            implementation="torch",
            num_proposal_samples_per_ray=(64, 32),
            num_nerf_samples_per_ray=32,
            log2_hashmap_size=15,
            num_levels=8,
            max_res=1024,
            proposal_warmup=iterations // 3,
            medium_num_layers=2,
            medium_hidden_dim=64,
        ),
        steps_per_eval_batch=100,
        steps_per_eval_image=500,
        steps_per_eval_all_images=100_000,
        steps_per_save=500,
        mixed_precision=False,
    )


seathru_nerf = MethodSpecification(
    config=seathru_nerf_config(),
    description="SeaThru-NeRF (Levy et al. 2023): NeRF in scattering media; separates the scene from water or fog.",
)

seathru_nerf_lite = MethodSpecification(
    config=seathru_nerf_lite_config(),
    description="SeaThru-NeRF sized for a CPU or laptop GPU (1024 rays, small hash grid, torch implementation).",
)
