"""Our methods and dataparser are what nerfstudio's CLIs list, not its placeholders."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def test_methods_come_from_our_package():
    from nerfstudio.configs.method_configs import all_descriptions, all_methods

    from seathru_nerfstudio.model import SeathruModelConfig

    for name in ("seathru-nerf", "seathru-nerf-lite"):
        assert isinstance(all_methods[name].pipeline.model, SeathruModelConfig), name
        assert "AkerBP" not in all_descriptions[name] and "pip install" not in all_descriptions[name]
    assert all_methods["seathru-nerf"].viewer.websocket_host == "127.0.0.1"


def test_seathru_dataparser_is_registered():
    from nerfstudio.configs.dataparser_configs import all_dataparsers

    from seathru_nerfstudio.data.seathru_dataparser import seathru_dataparser

    assert type(all_dataparsers["seathru-data"]) is type(seathru_dataparser.config)


def test_ns_train_help_lists_both_methods():
    env = dict(os.environ, COLUMNS="250", PYTHONWARNINGS="ignore")
    ns_train = Path(sys.executable).parent / "ns-train"
    result = subprocess.run([str(ns_train), "--help"], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    text = result.stdout
    assert "seathru-nerf-lite" in text and "SeaThru-NeRF sized for a CPU" in text
    assert "separates the scene from water" in text
    assert "AkerBP" not in text
