"""Method specs of the benchmark: ``NAME[:key=value,key=value...]`` -> a ``TrainerConfig``.

``NAME`` is ``seathru-nerf-lite``, ``seathru-nerf``, ``nerfacto`` (nerfacto at the capacity
of ``seathru-nerf-lite``, see :func:`matched_nerfacto_config`) or any other method that
nerfstudio has registered (its own config, moved to the CPU when there is no GPU).

Overrides are ``ns-train`` flags in short: tyro parses them against the method's
``TrainerConfig`` exactly as ``ns-train NAME`` parses its command line. ``key=value`` is
``--pipeline.model.key value`` for a bare key (``quadrature=paper``) and ``--key value`` for a
dotted path from the ``TrainerConfig`` (``pipeline.datamanager.train_num_rays_per_batch=2048``,
dictionary keys included: ``optimizers.medium.optimizer.lr=0.05``); keys under
``pipeline.datamanager.dataparser.`` are the dataparser's own flags (those after ns-train's
dataparser subcommand). Values are read as ns-train reads them; ``true``/``false`` in any case
are ``True``/``False``, ``None`` is ``None`` (lower-case ``none`` stays a string: it is a medium
model, ``medium_model=none``), and a tuple is written ``a|b|c``. ``ns-train NAME
--help`` lists every flag.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import hashlib
import io
import re
from typing import Any, Dict, List, Tuple

import tyro

from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

MATCHED_NERFACTO_KEEPS_OWN = ("background_color",)
"""nerfacto fields *not* copied from seathru-nerf-lite: nerfacto keeps its default
``last_sample`` background, which lets it paint open water with the colour of its farthest
sample (black would force it to build a wall of water colour). SeaThru reads its own
``background_color`` only in its ``none`` model; with a medium the water is the background."""


def matched_nerfacto_config() -> TrainerConfig:
    """nerfacto with everything of ``seathru-nerf-lite`` that nerfacto has.

    Same trainer, optimizers and schedules, seed, datamanager (``ParallelDataManager``
    [``LinearImageDataset``]: 16-bit images at full precision, 1024 rays), and every
    ``NerfactoModelConfig`` field: torch implementation, proposal samples (64, 32), 32 NeRF
    samples, hash 2^15 x 8 levels up to 1024, no appearance embedding, no camera optimizer,
    no distortion loss, same near/far and init density. What stays different is the method
    itself: no medium field, nerfacto's plain L2 loss (seathru: RawNeRF relative L2 + the
    binary transmittance prior), nerfacto's ``last_sample`` background, and nerfstudio's own
    ``VanillaPipeline`` (``SeathruPipeline`` manages a SeaThru model's water controls).
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
    config.pipeline = VanillaPipelineConfig(datamanager=config.pipeline.datamanager, model=NerfactoModelConfig(**kwargs))
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
        raise MethodSpecError(f"unknown method {name!r}; known: {', '.join(known)}")
    config = copy.deepcopy(all_methods[name])
    config.machine = ours._machine()
    return config


class MethodSpecError(ValueError):
    """A method spec names no known method, or tyro cannot parse its overrides."""


DATAPARSER_PREFIX = "pipeline.datamanager.dataparser."


def parse_spec(spec: str) -> Tuple[str, Dict[str, str]]:
    """``"seathru-nerf-lite:quadrature=paper,medium_model=basic"`` -> (name, overrides)."""
    name, _, rest = spec.partition(":")
    overrides: Dict[str, str] = {}
    for item in filter(None, (part.strip() for part in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or not key:
            raise MethodSpecError(f"method {spec!r}: override {item!r} is not key=value")
        overrides[key.strip()] = value.strip()
    if not name:
        raise MethodSpecError(f"method {spec!r}: empty name")
    return name, overrides


def _flag_values(text: str) -> List[str]:
    return [item.capitalize() if item.lower() in ("true", "false") else item for item in text.split("|")]


def override_flags(overrides: Dict[str, str]) -> Tuple[List[str], List[str]]:
    """The ns-train flags of ``overrides``: (``TrainerConfig`` flags, dataparser flags)."""
    trainer: List[str] = []
    dataparser: List[str] = []
    for key, text in overrides.items():
        if key.startswith(DATAPARSER_PREFIX):
            dataparser += [f"--{key[len(DATAPARSER_PREFIX):]}", *_flag_values(text)]
        else:
            trainer += [f"--{key if '.' in key else 'pipeline.model.' + key}", *_flag_values(text)]
    return trainer, dataparser


def _tyro_error(text: str) -> str:
    """The reason in tyro's error box (the section between its first two rules), one line."""
    sections = re.split(r"\n\s*-{10,}\s*\n", text)
    return " ".join((sections[1] if len(sections) > 1 else text).split())


def _parse(spec: str, name: str, default: Any, flags: List[str]) -> Any:
    """``default`` with ``flags`` applied by tyro (ns-train's flag syntax); tyro's message, which
    it prints before exiting, becomes a :class:`MethodSpecError`."""
    messages = io.StringIO()
    try:
        with contextlib.redirect_stdout(messages), contextlib.redirect_stderr(messages):
            return tyro.cli(tyro.conf.FlagConversionOff[type(default)], default=default, args=flags, prog=f"ns-train {name}")
    except SystemExit:
        raise MethodSpecError(
            f"method {spec!r}: {_tyro_error(messages.getvalue())} (the overrides are read as `ns-train {name}` "
            "flags; see its --help)"
        ) from None


def build_config(spec: str) -> TrainerConfig:
    """The ``TrainerConfig`` of a method spec, with its overrides applied."""
    name, overrides = parse_spec(spec)
    trainer_flags, dataparser_flags = override_flags(overrides)
    config = _parse(spec, name, _base_config(name), trainer_flags)
    if dataparser_flags:
        datamanager = config.pipeline.datamanager
        datamanager.dataparser = _parse(spec, name, datamanager.dataparser, dataparser_flags)
    return config


MAX_LABEL_CHARS = 120
"""Longest method label used as a directory name (file systems stop at 255 bytes per name)."""


def method_label(spec: str) -> str:
    """A file-name-safe label of a spec, unique per spec: a spec with many overrides is cut to
    ``MAX_LABEL_CHARS`` and ends in a hash of the whole spec."""
    label = "".join(c if c.isalnum() or c in "-_." else "_" for c in spec)
    if len(label) <= MAX_LABEL_CHARS:
        return label
    digest = hashlib.sha1(spec.encode()).hexdigest()[:10]
    return f"{label[: MAX_LABEL_CHARS - len(digest) - 1]}-{digest}"
