"""Method specs of the benchmark: ``NAME[:key=value,key=value...]`` -> a ``TrainerConfig``.

``NAME`` is ``seathru-nerf-lite``, ``seathru-nerf``, ``nerfacto`` (nerfacto at the capacity
of ``seathru-nerf-lite``, see :func:`matched_nerfacto_config`) or any other method that
nerfstudio has registered (its own config, moved to the CPU when there is no GPU).

Overrides: a bare ``key`` is a field of ``pipeline.model`` (``quadrature=paper``,
``medium_model=basic``); a dotted key is a path from the ``TrainerConfig``
(``pipeline.datamanager.train_num_rays_per_batch=2048``). Values are parsed to the type of
the current value (bool, int, float, str, tuples as ``a|b|c``).
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any, Dict, List, Tuple

from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.nerfacto import NerfactoModelConfig

MATCHED_NERFACTO_KEEPS_OWN = ("background_color",)
"""nerfacto fields *not* copied from seathru-nerf-lite: nerfacto keeps its default
``last_sample`` background, which lets it paint open water with the colour of its farthest
sample (black, seathru's choice, would force it to build a wall of water colour)."""


def matched_nerfacto_config() -> TrainerConfig:
    """nerfacto with everything of ``seathru-nerf-lite`` that nerfacto has.

    Same trainer, optimizers and schedules, seed, datamanager (``ParallelDataManager``
    [``LinearImageDataset``]: 16-bit images at full precision, 1024 rays), and every
    ``NerfactoModelConfig`` field: torch implementation, proposal samples (64, 32), 32 NeRF
    samples, hash 2^15 x 8 levels up to 1024, no appearance embedding, no camera optimizer,
    no distortion loss, same near/far and init density. What stays different is the method
    itself: no medium field, nerfacto's plain L2 loss (seathru: RawNeRF relative L2 + the
    binary transmittance prior), and nerfacto's ``last_sample`` background.
    """
    from seathru_nerfstudio.config import seathru_nerf_lite_config

    config = seathru_nerf_lite_config()
    config.method_name = "nerfacto"
    seathru_model = config.pipeline.model
    kwargs = {}
    for f in dataclasses.fields(NerfactoModelConfig):
        if f.name == "_target" or f.name in MATCHED_NERFACTO_KEEPS_OWN or not f.init:
            continue
        kwargs[f.name] = copy.deepcopy(getattr(seathru_model, f.name))
    config.pipeline.model = NerfactoModelConfig(**kwargs)
    return config


def _base_config(name: str) -> TrainerConfig:
    from seathru_nerfstudio import config as ours

    if name == "seathru-nerf-lite":
        return ours.seathru_nerf_lite_config()
    if name == "seathru-nerf":
        return ours.seathru_nerf_config()
    if name == "nerfacto":
        return matched_nerfacto_config()
    from nerfstudio.configs.method_configs import all_methods

    if name not in all_methods:
        known = sorted({"seathru-nerf-lite", "seathru-nerf", "nerfacto", *all_methods})
        raise ValueError(f"unknown method {name!r}; known: {', '.join(known)}")
    config = copy.deepcopy(all_methods[name])
    config.machine = ours._machine()
    return config


def parse_spec(spec: str) -> Tuple[str, Dict[str, str]]:
    """``"seathru-nerf-lite:quadrature=paper,medium_model=basic"`` -> (name, overrides)."""
    name, _, rest = spec.partition(":")
    overrides: Dict[str, str] = {}
    for item in filter(None, (part.strip() for part in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or not key:
            raise ValueError(f"method {spec!r}: override {item!r} is not key=value")
        overrides[key.strip()] = value.strip()
    if not name:
        raise ValueError(f"method {spec!r}: empty name")
    return name, overrides


def _convert(current: Any, text: str, where: str) -> Any:
    if isinstance(current, bool):
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"{where}: expected a boolean, got {text!r}")
    if isinstance(current, int):
        return int(text)
    if isinstance(current, float):
        return float(text)
    if isinstance(current, tuple):
        items = text.split("|")
        kind = type(current[0]) if current else str
        return tuple(kind(x) for x in items)
    if current is None:
        for kind in (int, float):
            try:
                return kind(text)
            except ValueError:
                pass
        return None if text.lower() == "none" else text
    if isinstance(current, str):
        return text
    raise ValueError(f"{where}: cannot override a field of type {type(current).__name__}")


def apply_overrides(config: TrainerConfig, overrides: Dict[str, str]) -> List[str]:
    """Apply ``overrides`` in place; returns them as ``path=value`` strings."""
    applied = []
    for key, text in overrides.items():
        path = key.split(".") if "." in key else ["pipeline", "model", key]
        target: Any = config
        for part in path[:-1]:
            if isinstance(target, dict) and part in target:  # e.g. optimizers.medium.optimizer.lr
                target = target[part]
                continue
            if not hasattr(target, part):
                raise ValueError(f"override {key!r}: no field {part!r}")
            target = getattr(target, part)
        leaf = path[-1]
        if not dataclasses.is_dataclass(target) or leaf not in {f.name for f in dataclasses.fields(target)}:
            raise ValueError(f"override {key!r}: {type(target).__name__} has no field {leaf!r}")
        value = _convert(getattr(target, leaf), text, key)
        setattr(target, leaf, value)
        applied.append(f"{'.'.join(path)}={value!r}")
    return applied


def build_config(spec: str) -> TrainerConfig:
    """The ``TrainerConfig`` of a method spec, with its overrides applied."""
    name, overrides = parse_spec(spec)
    config = _base_config(name)
    apply_overrides(config, overrides)
    return config


def method_label(spec: str) -> str:
    """A file-name-safe label of a spec."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in spec)
