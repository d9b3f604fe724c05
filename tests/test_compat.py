"""``compat.load_checkpoint`` reads a nerfstudio checkpoint with torch's safe loader by itself,
whatever was imported or registered before (the tests run in a random order)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seathru_nerfstudio.compat import load_checkpoint


def test_a_checkpoint_with_numpy_scalars_loads_without_any_earlier_registration(tmp_path):
    """A checkpoint holding NumPy scalars, as nerfstudio's schedulers leave in it: the safe
    loader refuses it with an empty allow-list; ``load_checkpoint`` registers the allow-list and
    reads it. The allow-list of the process is restored afterwards."""
    path = tmp_path / "step-000000001.ckpt"
    torch.save({"step": 1, "schedulers": {"fields": {"base_lrs": [np.float64(0.01)], "last_lr": np.float32(0.5)}}}, path)
    before = torch.serialization.get_safe_globals()
    torch.serialization.clear_safe_globals()
    try:
        with pytest.raises(Exception, match="(?i)unsupported global|weights_only"):
            torch.load(path, map_location="cpu", weights_only=True)
        state = load_checkpoint(path)
    finally:
        torch.serialization.clear_safe_globals()
        torch.serialization.add_safe_globals(before)
    assert state["step"] == 1
    assert state["schedulers"]["fields"]["base_lrs"] == [0.01] and state["schedulers"]["fields"]["last_lr"] == np.float32(0.5)
