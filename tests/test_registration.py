"""Our methods and dataparser are what nerfstudio's CLIs list, not its placeholders."""

from __future__ import annotations

import sys

import pytest


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


def test_ns_train_help_lists_both_methods(monkeypatch, capsys):
    """nerfstudio's ns-train entry point (in-process: the CLI's start-up is the same import)."""
    from nerfstudio.scripts import train

    monkeypatch.setenv("COLUMNS", "250")
    monkeypatch.setattr(sys, "argv", ["ns-train", "--help"])
    with pytest.raises(SystemExit) as exit_info:
        train.entrypoint()
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    assert "seathru-nerf-lite" in text and "SeaThru-NeRF sized for a CPU" in text
    assert "separates the scene from water" in text
    assert "AkerBP" not in text
