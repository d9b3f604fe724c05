"""A pixel sampler whose rays follow the run's seed, also inside nerfstudio's data worker.

nerfstudio's ``ParallelDataManager`` samples the training rays in a spawned process whose random
generators nobody seeds, so two runs with the same ``--machine.seed`` train on different rays
and end apart. On the tiny scene of ``tests/test_decomposition.py`` that spread was large: the
clean image's rise over training measured anywhere from +0.1 to +1.7 dB on unchanged code
(2026-11-25, before c85090d). With this sampler a run is repeatable; different seeds still give different runs.
"""

from __future__ import annotations

import hashlib
import multiprocessing
import random
from dataclasses import dataclass, field
from typing import Dict, Optional, Type

import torch

from nerfstudio.data.pixel_samplers import PixelSampler, PixelSamplerConfig


def stream_seed(run_seed: int, process_name: str) -> int:
    """The seed of one process's ray stream, in [0, 2^63): a hash of the run's seed and the
    process's name, so that several data workers (``num_processes`` > 1, named
    ``DataProcessor-1``, ``-2``, ... in the order a run starts them) do not draw the same rays."""
    digest = hashlib.blake2b(f"{int(run_seed)}:{process_name}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1


@dataclass
class SeededPixelSamplerConfig(PixelSamplerConfig):
    """nerfstudio's pixel sampler on a random stream of its own."""

    _target: Type = field(default_factory=lambda: SeededPixelSampler)
    seed: Optional[int] = None
    """Seed of the ray stream. None: the seed torch holds where the sampler is built, which is
    the run's ``machine.seed`` (ns-train and seathru-bench seed torch before they build the
    datamanager)."""


class SeededPixelSampler(PixelSampler):
    """Draws from private torch and Python random states, seeded from the run's seed and the
    name of the process that samples; the global generators of that process are left as they
    were. Covers CPU draws, which is where nerfstudio's data worker samples."""

    config: SeededPixelSamplerConfig

    def __init__(self, config: SeededPixelSamplerConfig, **kwargs) -> None:
        super().__init__(config, **kwargs)
        self.run_seed = config.seed if config.seed is not None else torch.initial_seed()
        self._torch_state: Optional[torch.Tensor] = None  # set in the process that samples
        self._python_state: Optional[tuple] = None

    def sample(self, image_batch: Dict):
        if self._torch_state is None:
            seed = stream_seed(self.run_seed, multiprocessing.current_process().name)
            self._torch_state = torch.Generator().manual_seed(seed).get_state()
            self._python_state = random.Random(seed).getstate()
        outer_python_state = random.getstate()
        with torch.random.fork_rng(devices=[]):
            torch.set_rng_state(self._torch_state)
            random.setstate(self._python_state)
            try:
                return super().sample(image_batch)
            finally:
                self._torch_state = torch.get_rng_state()
                self._python_state = random.getstate()
                random.setstate(outer_python_state)
