"""The known upstream warnings are silenced by message and module; everything else still shows."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

import pytest

from seathru_nerfstudio.quiet import (
    UPSTREAM_WARNINGS,
    KnownWarning,
    child_environment,
    pythonwarnings,
    silence_upstream_warnings,
)


def _shown(message: str, category: type[Warning], module: str) -> bool:
    """Whether a warning issued as if from ``module`` gets through the current filters."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.warn_explicit(message, category, filename=f"{module.replace('.', '/')}.py", lineno=1, module=module)
    return bool(caught)


def test_known_upstream_warnings_are_silenced_and_others_still_show():
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        silence_upstream_warnings()
        for known in UPSTREAM_WARNINGS:
            assert not _shown(known.message + " (details)", known.category, known.module), known
            # the same text from another module, or of another category, is not ours to hide
            assert _shown(known.message, known.category, "seathru_nerfstudio.model"), known
            other = DeprecationWarning if known.category is not DeprecationWarning else UserWarning
            assert _shown(known.message, other, known.module), known
        assert _shown("depth loss skipped: no depth_file_path", UserWarning, "seathru_nerfstudio.model")
        assert _shown("some new nerfstudio warning", UserWarning, "nerfstudio.cameras.cameras")


def test_child_processes_get_the_same_filters():
    """nerfstudio's real import-time warnings (custom_fwd/custom_bwd) disappear from a child
    started with :func:`child_environment`; a warning of ours in the same child still shows."""
    script = (
        "import warnings, nerfstudio.field_components.activations\n"
        "warnings.warn('ours: still shown', UserWarning)\n"
    )
    environ = {k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"}
    loud = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=environ, timeout=300)
    quiet = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=child_environment(environ), timeout=300
    )
    assert loud.returncode == quiet.returncode == 0, quiet.stderr
    assert "custom_fwd" in loud.stderr and "custom_bwd" in loud.stderr  # the upstream warning exists
    assert "custom_fwd" not in quiet.stderr and "custom_bwd" not in quiet.stderr
    assert "ours: still shown" in quiet.stderr
    assert "Invalid -W option" not in quiet.stderr  # every filter survives PYTHONWARNINGS' syntax


def test_the_users_own_pythonwarnings_keep_precedence():
    value = pythonwarnings("error::UserWarning")
    assert value.endswith(",error::UserWarning")  # later -W options take precedence
    assert child_environment({"PYTHONWARNINGS": "error::UserWarning"})["PYTHONWARNINGS"] == value


def test_a_filter_that_pythonwarnings_would_split_is_refused():
    with pytest.raises(ValueError, match="cannot hold"):
        KnownWarning(UserWarning, "To copy construct from a tensor, it is recommended", "nerfstudio.cameras.camera_utils")
