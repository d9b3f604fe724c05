"""Known upstream warnings that a user of our commands can do nothing about, silenced one by one.

Each filter names the warning's category, the start of its message and the exact module that
issues it (as Python's ``-W`` / ``PYTHONWARNINGS`` options match them), so the same warning
from anywhere else, and every warning of ours, still shows. Our entry points call
:func:`silence_upstream_warnings`; child processes (the bench worker, ``ns-train``,
``ns-eval`` and ``ns-render`` in ``scripts/quickstart.sh``) get :func:`pythonwarnings` in
their ``PYTHONWARNINGS``. ``python -m seathru_nerfstudio.quiet`` prints that value (the
caller's own ``PYTHONWARNINGS`` kept at the end).
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from typing import Mapping, Optional, Type


@dataclass(frozen=True)
class KnownWarning:
    category: Type[Warning]
    message: str
    """The start of the message (case-insensitive)."""
    module: str
    """The module the warning is attributed to, exactly."""

    def __post_init__(self) -> None:
        for text in (self.message, self.module):
            if ":" in text or "," in text:  # PYTHONWARNINGS separates fields by ":" and filters by ","
                raise ValueError(f"{text!r}: a warning filter for PYTHONWARNINGS cannot hold ':' or ','")


_UPSTREAM = [
    # nerfstudio 1.1.5 indexes tensors with lists: torch warns on every camera ray bundle.
    (UserWarning, "Using a non-tuple sequence for multidimensional indexing is deprecated", "nerfstudio.cameras.cameras"),
    # nerfstudio decorates with torch.jit.script and torch.cuda.amp's custom_fwd/custom_bwd, and
    # builds torch.cuda.amp's GradScaler (we use none of them).
    (FutureWarning, "`torch.jit.script` is deprecated", "torch.jit._script"),
    (FutureWarning, "`torch.cuda.amp.custom_fwd(args...)` is deprecated", "nerfstudio.field_components.activations"),
    (FutureWarning, "`torch.cuda.amp.custom_bwd(args...)` is deprecated", "nerfstudio.field_components.activations"),
    (FutureWarning, "`torch.cuda.amp.GradScaler(args...)` is deprecated", "nerfstudio.engine.trainer"),
    # nerfstudio imports torchmetrics' SAM from its old place.
    (FutureWarning, "Importing `spectral_angle_mapper` from `torchmetrics.functional`", "torchmetrics.utilities.prints"),
    # nerfstudio's camera path interpolation (ns-render) copy-constructs tensors.
    (UserWarning, "To copy construct from a tensor", "nerfstudio.cameras.camera_utils"),
    # nerfstudio's datamanagers ask for 4 image-loader processes per device, whatever the core count.
    (UserWarning, "This DataLoader will create", "torch.utils.data.dataloader"),
    # nerfstudio's event writer turns training scalars into floats while they still carry a graph.
    (UserWarning, "Converting a tensor with requires_grad=True to a scalar", "nerfstudio.utils.writer"),
    # nerfstudio steps every scheduler each iteration, also those whose optimiser had nothing to do.
    (UserWarning, "Detected call of `lr_scheduler.step()` before `optimizer.step()`", "nerfstudio.engine.optimizers"),
]
UPSTREAM_WARNINGS = tuple(KnownWarning(category, message, module) for category, message, module in _UPSTREAM)


def silence_upstream_warnings() -> None:
    """Ignore :data:`UPSTREAM_WARNINGS` in this process (as ``-W`` would)."""
    for known in UPSTREAM_WARNINGS:
        warnings.filterwarnings(
            "ignore", message=re.escape(known.message), category=known.category, module=re.escape(known.module) + r"\Z"
        )


def pythonwarnings(existing: Optional[str] = None) -> str:
    """A ``PYTHONWARNINGS`` value that ignores :data:`UPSTREAM_WARNINGS`, after ``existing`` (the
    user's own value, which then keeps precedence for anything it names)."""
    ours = [f"ignore:{k.message}:{k.category.__name__}:{k.module}" for k in UPSTREAM_WARNINGS]
    return ",".join(ours + ([existing] if existing else []))


def child_environment(environ: Mapping[str, str]) -> dict[str, str]:
    """``environ`` with :func:`pythonwarnings` as ``PYTHONWARNINGS``, for a child process."""
    return {**environ, "PYTHONWARNINGS": pythonwarnings(environ.get("PYTHONWARNINGS"))}


if __name__ == "__main__":
    import os

    print(pythonwarnings(os.environ.get("PYTHONWARNINGS")))
