"""``scripts/gpu_check.py`` without a GPU: its one-line refusal, and the matched full nerfacto it runs."""

from __future__ import annotations

import sys
from pathlib import Path

import torch


def load_gpu_check():
    import importlib.util

    path = Path(__file__).parents[1] / "scripts" / "gpu_check.py"
    spec = importlib.util.spec_from_file_location("gpu_check", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_gpu_check_stops_with_one_line_without_cuda_or_tiny_cuda_nn(monkeypatch, capsys):
    gpu_check = load_gpu_check()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert gpu_check.main([]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no CUDA GPU" in err
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setitem(sys.modules, "tinycudann", None)  # import fails
    assert gpu_check.main([]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "tiny-cuda-nn is not usable" in err


def test_gpu_check_matches_nerfacto_to_the_full_method():
    import dataclasses

    from nerfstudio.models.nerfacto import NerfactoModelConfig

    from seathru_nerfstudio.bench.methods import MATCHED_NERFACTO_KEEPS_OWN
    from seathru_nerfstudio.config import seathru_nerf_config

    seathru = seathru_nerf_config()
    nerfacto = load_gpu_check().matched_full_nerfacto(seathru)
    assert type(nerfacto.pipeline.model) is NerfactoModelConfig
    for f in dataclasses.fields(NerfactoModelConfig):
        if f.init and f.name != "_target" and f.name not in MATCHED_NERFACTO_KEEPS_OWN:
            assert getattr(nerfacto.pipeline.model, f.name) == getattr(seathru.pipeline.model, f.name), f.name
    assert nerfacto.pipeline.datamanager.train_num_rays_per_batch == 16384
    assert nerfacto.mixed_precision == seathru.mixed_precision and nerfacto.optimizers == seathru.optimizers
