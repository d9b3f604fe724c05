"""Compatibility of nerfstudio 1.1.5 with torch >= 2.6.

torch 2.6 made ``torch.load`` default to ``weights_only=True``. nerfstudio's checkpoints hold
NumPy scalars (learning rates from its schedulers), so ``ns-eval``, ``ns-render``,
``ns-viewer --load-config`` and resuming all fail with ``Unsupported global``. Rather than
turning the safe loader off, we allow-list exactly the NumPy types those checkpoints use.
"""

from __future__ import annotations

import os
from typing import Any, Dict

import numpy as np
import torch


def _numpy_scalar_reconstructor():
    try:  # NumPy >= 2 keeps it in numpy._core
        from numpy._core.multiarray import scalar  # type: ignore[attr-defined]
    except ImportError:  # pragma: no cover - NumPy 1.x
        from numpy.core.multiarray import scalar  # type: ignore[no-redef]
    return scalar


def allow_nerfstudio_checkpoints() -> None:
    """Let ``torch.load(weights_only=True)`` read nerfstudio checkpoints (idempotent)."""
    add_safe_globals = getattr(torch.serialization, "add_safe_globals", None)
    if add_safe_globals is None:  # torch < 2.4 loads them anyway
        return
    dtypes = [np.dtype, *(type(np.dtype(t)) for t in (np.float64, np.float32, np.int64, np.int32, np.bool_))]
    add_safe_globals([_numpy_scalar_reconstructor(), *dtypes])


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> Dict[str, Any]:
    """A nerfstudio checkpoint (``step-*.ckpt``: ``step``, ``pipeline``, ``optimizers``,
    ``schedulers``, ``scalers``) read with torch's safe loader, the allow-list registered first:
    it does not depend on something else having imported :mod:`seathru_nerfstudio.config`."""
    allow_nerfstudio_checkpoints()
    return torch.load(path, map_location=map_location, weights_only=True)
