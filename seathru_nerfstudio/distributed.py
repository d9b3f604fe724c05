"""Multi-process training without GPUs: nerfstudio's ``Trainer`` over a Gloo process group.

Why this exists: on GPUs, ``ns-train seathru-nerf --machine.num-devices N`` runs nerfstudio's own
launcher (NCCL) and needs nothing from us. On CPUs that launcher cannot run: nerfstudio 1.1.5
asserts CUDA in ``_distributed_worker`` ("cuda is not available"), and its ``VanillaPipeline``
wraps the model as ``DDP(model, device_ids=[local_rank])``, which torch refuses for a CPU module
("device_ids ... only work with ... GPU modules"). This module gets past both without patching
nerfstudio:

* :class:`GlooSeathruPipeline` is our pipeline, wrapped in ``DDP`` without ``device_ids`` when the
  model is not on a GPU (what torch requires for CPU modules); on a GPU it is exactly
  :class:`~seathru_nerfstudio.pipeline.SeathruPipeline`.
* :func:`launch` starts one process per device with ``torch.multiprocessing.spawn``, joins them in a
  Gloo process group and runs nerfstudio's own ``train_loop`` (seeding, ``Trainer.setup``,
  ``Trainer.train``) in each, with nerfstudio's ``local_rank``/``world_size``.

Usage, with the same arguments as ``ns-train``::

    python -m seathru_nerfstudio.distributed seathru-nerf-lite --data DATA \\
        --machine.device-type cpu --machine.num-devices 2

``--machine.device-type cuda`` (or a single process) hands the command to nerfstudio's ``ns-train``
unchanged. Only rank 0 writes checkpoints, event logs and runs the viewer (nerfstudio's rule).
"""

from __future__ import annotations

import os
import socket
from datetime import timedelta
from typing import Any, Literal, Optional

import torch
import yaml
import torch.distributed as dist
import torch.multiprocessing as mp
from torch.nn.parallel import DistributedDataParallel as DDP

from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from seathru_nerfstudio.pipeline import SeathruPipeline

DEFAULT_TIMEOUT = timedelta(minutes=30)


class GlooSeathruPipeline(SeathruPipeline):
    """``SeathruPipeline`` that can be data-parallel on CPUs.

    nerfstudio's ``VanillaPipeline.__init__`` wraps the model in ``DDP`` with
    ``device_ids=[local_rank]``, valid for GPU modules only. For a model that is not on a CUDA
    device we let the parent build the pipeline as a single process (``world_size=1``: the only
    other use of it there is the number of eval-loader workers), then wrap the model in ``DDP``
    the way torch wants CPU modules wrapped, with nerfstudio's ``find_unused_parameters=True``.
    """

    def __init__(
        self,
        config,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: Optional[Any] = None,
    ):
        on_gpu = torch.device(device).type == "cuda"
        super().__init__(config, device, test_mode, world_size if on_gpu else 1, local_rank, grad_scaler)
        if world_size > 1 and not on_gpu:
            if not dist.is_initialized():
                raise RuntimeError(
                    f"world_size={world_size} needs a torch.distributed process group; start training with "
                    "`python -m seathru_nerfstudio.distributed ...` (or call seathru_nerfstudio.distributed.launch)"
                )
            self.world_size = world_size
            self._model = DDP(self._model, find_unused_parameters=True)  # type: ignore[assignment]
            dist.barrier()


def use_gloo_pipeline(config: TrainerConfig) -> TrainerConfig:
    """Make ``config`` (one of our methods) build :class:`GlooSeathruPipeline`. In place; returns it."""
    target = config.pipeline._target
    if not (isinstance(target, type) and issubclass(target, SeathruPipeline)):
        raise ValueError(
            f"multi-process CPU training supports the seathru methods only (pipeline {target!r} is not a SeathruPipeline)"
        )
    if not issubclass(target, GlooSeathruPipeline):
        config.pipeline._target = GlooSeathruPipeline
    return config


def free_local_url() -> str:
    """A ``tcp://127.0.0.1:PORT`` rendezvous address with a port that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return f"tcp://127.0.0.1:{sock.getsockname()[1]}"


def _worker(
    local_rank: int,
    config: TrainerConfig,
    world_size: int,
    machine_rank: int,
    dist_url: str,
    threads: int,
    timeout: timedelta,
) -> None:
    """One rank: join the Gloo group, run nerfstudio's ``train_loop``, leave the group."""
    from nerfstudio.scripts.train import train_loop  # nerfstudio's: seed + Trainer.setup() + Trainer.train()

    torch.set_num_threads(threads)
    global_rank = machine_rank * config.machine.num_devices + local_rank
    dist.init_process_group("gloo", init_method=dist_url, world_size=world_size, rank=global_rank, timeout=timeout)
    try:
        train_loop(local_rank, world_size, config, global_rank)
        dist.barrier()
    finally:
        dist.destroy_process_group()


def launch(config: TrainerConfig, timeout: timedelta = DEFAULT_TIMEOUT) -> None:
    """Train ``config`` with ``config.machine.num_devices`` processes on this machine, in a Gloo
    group of ``num_devices * num_machines`` processes (``machine_rank``, ``dist_url`` as in
    nerfstudio; ``dist_url="auto"`` picks a free local port, single machine only)."""
    machine = config.machine
    world_size = machine.num_devices * machine.num_machines
    if world_size < 2:
        raise ValueError("launch() is for 2 or more processes; use ns-train for one")
    dist_url = machine.dist_url
    if dist_url == "auto":
        if machine.num_machines > 1:
            raise ValueError("--machine.dist-url auto works on one machine only; give tcp://HOST:PORT of machine 0")
        dist_url = free_local_url()
    use_gloo_pipeline(config)
    threads = max(1, (os.cpu_count() or 1) // machine.num_devices)
    CONSOLE.log(f"Gloo: {machine.num_devices} processes here, {world_size} in all, {threads} torch thread(s) each")
    mp.spawn(
        _worker,
        args=(config, world_size, machine.machine_rank, dist_url, threads, timeout),
        nprocs=machine.num_devices,
        join=True,
    )


def main(config: TrainerConfig) -> None:
    """``ns-train``'s ``main``, with CPU/Gloo multi-process runs launched by :func:`launch`."""
    from nerfstudio.scripts import train as ns_train

    if config.load_config:
        CONSOLE.log(f"Loading pre-set config from: {config.load_config}")
        config = yaml.load(config.load_config.read_text(), Loader=yaml.Loader)
    world_size = config.machine.num_devices * config.machine.num_machines
    if config.machine.device_type == "cuda" or world_size == 1:
        ns_train.main(config)  # nerfstudio's path, unchanged (NCCL on GPUs)
        return
    if config.data:
        config.pipeline.datamanager.data = config.data
    config.set_timestamp()
    config.print_to_terminal()
    config.save_config()
    launch(config)


def entrypoint() -> None:
    """``python -m seathru_nerfstudio.distributed METHOD [ns-train options]``."""
    import tyro

    from nerfstudio.configs.config_utils import convert_markup_to_ansi
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    tyro.extras.set_accent_color("bright_yellow")
    main(tyro.cli(AnnotatedBaseConfigUnion, description=convert_markup_to_ansi(__doc__ or "")))


if __name__ == "__main__":
    entrypoint()
