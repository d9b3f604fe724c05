"""The seeded pixel sampler: repeatable rays, in the data worker's process too, without touching
the global generators."""

from __future__ import annotations

import multiprocessing
import random

import torch

from seathru_nerfstudio.data.seeded_sampler import SeededPixelSampler, SeededPixelSamplerConfig, stream_seed

IMAGES = {"image": torch.rand(4, 12, 16, 3), "image_idx": torch.arange(4)}


def _sampler(seed=None, rays=64):
    return SeededPixelSamplerConfig(seed=seed).setup(num_rays_per_batch=rays)


def _indices(sampler, batches=3):
    return torch.stack([sampler.sample(IMAGES)["indices"] for _ in range(batches)])


def _indices_in_a_spawned_process(sampler, results):
    results.put(_indices(sampler).tolist())  # plain lists: no tensor sharing across processes


def test_the_same_seed_gives_the_same_rays_and_another_seed_other_rays():
    first, again, other = _indices(_sampler(3)), _indices(_sampler(3)), _indices(_sampler(4))
    assert torch.equal(first, again)
    assert not torch.equal(first, other)
    assert not torch.equal(first[0], first[1])  # the stream moves on between batches


def test_without_a_seed_it_follows_the_seed_torch_was_given():
    torch.manual_seed(11)
    first = _indices(_sampler())
    torch.manual_seed(11)
    again = _indices(_sampler())
    torch.manual_seed(12)
    other = _indices(_sampler())
    assert torch.equal(first, again) and not torch.equal(first, other)


def test_the_global_generators_are_left_as_they_were():
    sampler = _sampler(5)
    torch.manual_seed(0)
    random.seed(0)
    expected = (torch.rand(3), random.random())
    torch.manual_seed(0)
    random.seed(0)
    sampler.sample(IMAGES)
    assert torch.equal(torch.rand(3), expected[0]) and random.random() == expected[1]


def test_the_sampled_indices_are_inside_the_images():
    indices = _indices(_sampler(1, rays=500)).reshape(-1, 3)
    assert indices.min() >= 0
    assert (indices.max(dim=0).values < torch.tensor([4, 12, 16])).all()


def test_a_spawned_worker_repeats_its_rays_and_differs_from_the_main_process():
    """As nerfstudio's ParallelDataManager does: the sampler is built (and seeded) in the main
    process and pickled into a spawned worker, whose own generators are unseeded."""
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    runs = []
    for _ in range(2):
        worker = context.Process(target=_indices_in_a_spawned_process, args=(_sampler(9), results), name="DataProcessor-1")
        worker.start()
        runs.append(torch.tensor(results.get(timeout=120)))
        worker.join(timeout=60)
        assert worker.exitcode == 0
    assert torch.equal(runs[0], runs[1])
    assert not torch.equal(runs[0], _indices(_sampler(9)))  # another process, another stream


def test_stream_seeds_differ_between_processes_and_fit_in_63_bits():
    seeds = {stream_seed(s, name) for s in (0, 1, 2**63) for name in ("MainProcess", "DataProcessor-1", "DataProcessor-2")}
    assert len(seeds) == 9
    assert all(0 <= s < 2**63 for s in seeds)
