"""The learned medium as data: ``medium.json`` beside a run's ``config.yml``, and one line for people.

What the file holds (``write_medium_report``; the trainer writes it at every checkpoint, and
``seathru-medium --load-config .../config.yml`` writes it for an existing run):

* ``beta_D``, ``beta_B``: attenuation and backscatter densities per channel (linear RGB) in
  1/world unit: the model's densities per scene unit times the dataparser scale (scene units per
  world unit). ``unit`` says what the world unit is: ``"metre"`` when the dataset declares it
  (``seathru-synth`` scenes: ``ground_truth/medium.json`` has ``"world_units": "m"``; any
  capture: ``"world_units": "m"`` in ``transforms.json``), else ``"world unit (scale
  unknown)"``: a COLMAP reconstruction has no scale, and its densities are per COLMAP unit.
* ``B_inf``: the veiling light (backscatter at infinity), linear RGB: that in front of the surfaces, which
  the formation model's ``B_inf (1 - e^{-beta_B z})`` reaches. ``B_inf_open_water`` (scene medium, where it is
  brighter): the open water's, whose excess reaches a ray only past all matter (:mod:`~seathru_nerfstudio.surface_veil`).
* ``attenuation_length``: ``1 / beta_D``, the distance over which the direct light falls to
  ``1/e`` (world units).
* ``medium_model``: the model in use (``auto``'s choice once it has decided; ``seathru``
  before), with the configured one.
* ``fit``: where the medium fit ran, the standard error of ``ln beta_D`` per channel and, to
  first order (``SE(beta) = beta SE(ln beta)``), of ``beta_D`` in 1/world unit, and which
  densities are held at their fit; that of ``ln beta_B`` given the veil, and
  ``ln_beta_B_per_ln_B_inf``, how many per cent ``beta_B`` moves per per cent of error in ``B_inf``
  (:func:`~seathru_nerfstudio.medium_fit.veil_sensitivity`; usually the larger error of the two).
* ``B_inf_rise`` (scene medium, where the open water was read brighter looking up): the veil of a
  ray whose unit direction has component ``u`` along ``vertical`` (the scene frame's up, from the
  training cameras: :mod:`~seathru_nerfstudio.vertical`) is
  ``B_inf (1 + gain (min(u, up_to_sin_elevation) - above_sin_elevation))`` above
  ``above_sin_elevation`` (per channel), and ``B_inf`` below it; ``B_inf_highest`` is its value at the top.
  ``B_inf`` itself is the veil looking down. The surfaces are seen through the backscatter rate
  ``B_inf beta_B`` in every direction: the rise is the far water's, higher up
  (:func:`~seathru_nerfstudio.rendering.depth_lit_backscatter_density`).
* ``B_inf_across`` (scene medium, where the open water was read to change round the horizon): a
  ray whose components along the two level axes ``level_axes`` are ``h`` sees the veil times
  ``max(0, 1 + Σ_j change_j (clamp(h_j, low_j, high_j) - mean_j))`` (``change``: one row per axis,
  per channel), at every range alike. ``B_inf`` and ``B_inf_rise`` are at the open water's mean
  heading (``h = mean``), where that factor is 1.
* ``medium_scope ray`` (the medium is an MLP of the ray direction): ``directions``, a table of
  the medium over a grid of view directions in the scene frame, elevations measured along
  ``vertical`` as above; the top-level values are then its mean over the training cameras' optical axes
  (or over the table's directions when no cameras are given).

The keys ``beta_D``, ``beta_B`` and ``B_inf`` (1/m) are those of ``seathru-synth``'s true
medium, so a metric run's file can start another run (``--pipeline.model.research.medium-oracle``).
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional

import torch
from jaxtyping import Float
from torch import Tensor

from seathru_nerfstudio.vertical import level_direction, level_frame

REPORT_NAME = "medium.json"
"""The file's name, beside ``config.yml``."""
METRE = "metre"
UNKNOWN_UNIT = "world unit (scale unknown)"
ELEVATIONS_DEG = (-90, -60, -30, 0, 30, 60, 90)
AZIMUTHS_DEG = tuple(range(0, 360, 45))


def world_unit(data: Optional[Path]) -> str:
    """``"metre"`` when the dataset at ``data`` (a folder or a ``transforms.json``) declares metric
    world units, else :data:`UNKNOWN_UNIT`. Unreadable files declare nothing."""
    if data is None:
        return UNKNOWN_UNIT
    data = Path(data)
    folder = data.parent if data.suffix == ".json" else data
    for candidate in (folder / "transforms.json", folder / "ground_truth" / "medium.json"):
        try:
            declared = json.loads(candidate.read_text()).get("world_units")
        except (OSError, ValueError, AttributeError):
            continue
        if str(declared).lower() in ("m", "metre", "meter", "metres", "meters"):
            return METRE
    return UNKNOWN_UNIT


def direction_grid(vertical: Optional[Float[Tensor, "3"]] = None) -> Float[Tensor, "n 3"]:
    """Unit directions at :data:`ELEVATIONS_DEG` x :data:`AZIMUTHS_DEG` (one at each pole), in the
    scene frame: elevation above the plane level to ``vertical`` (the scene's unit up; default
    ``+z``), azimuth from :func:`~seathru_nerfstudio.vertical.level_direction` towards ``vertical × it``."""
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) if vertical is None else vertical.detach().double().cpu()
    frame = torch.cat([level_frame(up), up[:, None]], dim=1)  # columns: the level axes, then up
    rows = []
    for elevation in ELEVATIONS_DEG:
        for azimuth in AZIMUTHS_DEG if abs(elevation) < 90 else (0,):
            e, a = math.radians(elevation), math.radians(azimuth)
            rows.append([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    return (torch.tensor(rows, dtype=torch.float64) @ frame.T).float()


@contextlib.contextmanager
def _trained_medium(model: Any) -> Iterator[None]:
    """The medium as trained: the viewer's water controls off while inside."""
    enabled = getattr(model, "medium_controls_enabled", False)
    model.medium_controls_enabled = False
    try:
        yield
    finally:
        model.medium_controls_enabled = enabled


def _per_world(model: Any, directions: Float[Tensor, "n 3"]) -> Dict[str, Float[Tensor, "n 3"]]:
    """The medium as rendered along ``directions`` (tied as the model in use): densities per world
    unit (per scene unit times ``model.world_scale``), veiling light linear."""
    with torch.no_grad(), _trained_medium(model):
        medium = model.medium(directions.to(model.device))
    scale = float(model.world_scale)
    return {
        "beta_D": medium.sigma_attn.double().cpu() * scale,
        "beta_B": medium.sigma_bs.double().cpu() * scale,
        "B_inf": medium.rgb.double().cpu(),
    }


def _numbers(values: Tensor) -> List[float]:
    return [float(v) for v in values.flatten()]


def _fit(model: Any, beta_d: Tensor) -> Optional[Dict[str, Any]]:
    """The fit's standard errors and holds, or ``None`` where no fit ran."""
    log_error = getattr(model, "fit_log_error", None)
    held = getattr(model, "densities_fitted", None)
    if log_error is None:
        return {"standard_error_ln_beta_D": None, "note": "this model records no standard errors"}
    log_error = log_error.detach().double().cpu()
    if not bool((log_error >= 0).all()):  # the model's -1 (or NaN): no fit ran
        return None
    fit: Dict[str, Any] = {
        "standard_error_ln_beta_D": _numbers(log_error),
        "standard_error_beta_D": _numbers(beta_d * log_error),
    }
    backscatter_error = getattr(model, "fit_backscatter_log_error", None)
    if backscatter_error is not None and bool((backscatter_error >= 0).all()):  # -1: a checkpoint from before it was kept
        fit["standard_error_ln_beta_B"] = _numbers(backscatter_error.detach().double().cpu())
        fit["ln_beta_B_per_ln_B_inf"] = _numbers(model.backscatter_veil_sensitivity.detach().double().cpu())
    if held is not None:
        fit["held_beta_D"] = [bool(v) for v in held[:3]]
        fit["held_beta_B"] = [bool(v) for v in held[3:]]
    return fit


def _veil_rise(model: Any) -> Optional[Dict[str, Any]]:
    """The scene medium's rise of the veil looking up (module docstring), or ``None`` where it has none."""
    field = getattr(model, "medium_field", None)
    gain = getattr(field, "veil_rise", None)
    if gain is None or not bool((gain > 0).any()):
        return None
    start, end = _numbers(field.veil_rise_from.detach().double().cpu()), float(field.veil_rise_to)
    vertical = field.vertical.detach().double().cpu()
    top = math.sqrt(max(0.0, 1.0 - end * end)) * level_direction(vertical) + end * vertical  # at the highest elevation
    return {
        "vertical": _numbers(vertical),
        "above_sin_elevation": start,
        "up_to_sin_elevation": end,
        "gain": _numbers(gain.detach().double().cpu()),
        "B_inf_highest": _numbers(_per_world(model, top[None].float())["B_inf"][0]),
    }


def _veil_across(model: Any) -> Optional[Dict[str, Any]]:
    """The scene medium's change of the veil round the horizon (module docstring), or ``None`` where it has none."""
    field = getattr(model, "medium_field", None)
    change = getattr(field, "veil_across", None)
    if change is None or not bool((change != 0).any()):
        return None
    return {
        "level_axes": [_numbers(axis) for axis in field.level_axes.detach().double().cpu().T],
        "mean": _numbers(field.veil_across_mean.detach().double().cpu()),
        "change": [_numbers(row) for row in change.detach().double().cpu()],
        "low": _numbers(field.veil_across_low.detach().double().cpu()),
        "high": _numbers(field.veil_across_high.detach().double().cpu()),
    }


def medium_report(
    model: Any,
    unit: str = UNKNOWN_UNIT,
    step: Optional[int] = None,
    view_directions: Optional[Float[Tensor, "m 3"]] = None,
) -> Dict[str, Any]:
    """The learned medium of ``model`` (a ``SeathruModel``) as a JSON-ready dict (module docstring).
    ``unit``: :func:`world_unit` of its dataset; ``view_directions``: the training cameras'
    optical axes (scene frame), over which a medium of the ray direction is averaged."""
    per = "1/m" if unit == METRE else "1/world unit"
    config = model.config
    scope = getattr(config, "medium_scope", "scene")
    report: Dict[str, Any] = {
        "step": step,
        "medium_model": model.medium_model,
        "medium_model_configured": config.medium_model,
        "medium_scope": scope,
        "unit": unit,
        "units": per,
        "dataparser_scale": float(model.world_scale),
    }
    if scope == "ray":
        grid = direction_grid(getattr(model, "vertical", None))
        table = _per_world(model, grid)
        average = _per_world(model, view_directions) if view_directions is not None else table
        report["average_over"] = "training cameras' optical axes" if view_directions is not None else "the table's directions"
        values = {key: value.mean(dim=0) for key, value in average.items()}
        report["directions"] = [
            {"direction": _numbers(grid[i]), **{key: _numbers(table[key][i]) for key in table}}
            for i in range(grid.shape[0])
        ]
    else:
        nadir = torch.tensor([[0.0, 0.0, -1.0]])
        values = {key: value[0] for key, value in _per_world(model, nadir).items()}
        if hasattr(getattr(model, "medium_field", None), "across_gain"):  # at the mean heading: without the factor
            with torch.no_grad():
                factor = model.medium_field.across_gain(nadir.to(model.device))[0].double().cpu()
            values["B_inf"] = torch.where(factor > 0, values["B_inf"] / factor.clamp_min(1e-12), values["B_inf"])
    report["beta_D"] = _numbers(values["beta_D"])
    report["beta_B"] = _numbers(values["beta_B"])
    surface_veil = getattr(getattr(model, "medium_field", None), "surface_veil", None)
    if scope == "scene" and surface_veil is not None and bool((surface_veil < 1).any()):
        report["B_inf_open_water"] = _numbers(values["B_inf"])
        values["B_inf"] = values["B_inf"] * surface_veil.detach().double().cpu()
    report["B_inf"] = _numbers(values["B_inf"])
    report["attenuation_length"] = [1.0 / b if b > 0 else None for b in report["beta_D"]]
    report["fit"] = _fit(model, values["beta_D"])
    rise = _veil_rise(model) if scope == "scene" else None
    if rise is not None:
        report["B_inf_rise"] = rise
    across = _veil_across(model) if scope == "scene" else None
    if across is not None:
        report["B_inf_across"] = across
    report["summary"] = summary_line(report)
    return report


def summary_line(report: Dict[str, Any]) -> str:
    """One line for people, e.g. ``medium seathru (step 1500): beta_D 1.3 1.2 0.9 /m, beta_B ...``."""
    per = "/m" if report["unit"] == METRE else "/world unit"
    show = lambda values: " ".join("-" if v is None else f"{v:.3g}" for v in values)  # noqa: E731
    step = "" if report.get("step") is None else f" (step {report['step']})"
    chosen = report["medium_model"]
    if report["medium_model_configured"] != chosen:
        chosen += f", {report['medium_model_configured']}'s choice"
    line = (
        f"medium {chosen}{step}: beta_D {show(report['beta_D'])} {per}, beta_B {show(report['beta_B'])} {per}, "
        f"B_inf {show(report['B_inf'])} (linear RGB)"
    )
    if report.get("B_inf_rise"):
        line += f", B_inf looking up to {show(report['B_inf_rise']['B_inf_highest'])}"
    if report["medium_scope"] == "ray":
        line += f", mean over {report['average_over']}"
    fit = report.get("fit")
    if fit and fit.get("standard_error_ln_beta_D") is not None:
        line += f"; fit: standard error of ln beta_D {show(fit['standard_error_ln_beta_D'])}"
    if fit and fit.get("ln_beta_B_per_ln_B_inf") is not None:
        line += f", of ln beta_B {show(fit['standard_error_ln_beta_B'])}; beta_B moves {show(fit['ln_beta_B_per_ln_B_inf'])} times an error of B_inf"
    if report["unit"] != METRE:
        line += " (world unit of unknown scale)"
    return line


def write_medium_report(
    model: Any,
    path: Path,
    data: Optional[Path] = None,
    step: Optional[int] = None,
    view_directions: Optional[Float[Tensor, "m 3"]] = None,
) -> Path:
    """Write :func:`medium_report` to ``path`` (a temporary file, then a rename); returns ``path``."""
    from seathru_nerfstudio.data.io import write_text_atomic

    report = medium_report(model, world_unit(data), step, view_directions)
    path = Path(path)
    write_text_atomic(path, json.dumps(report, indent=2) + "\n")
    return path


def optical_axes(cameras: Any) -> Float[Tensor, "m 3"]:
    """The cameras' viewing directions (their ``-z`` axis; nerfstudio's OpenGL convention)."""
    return -cameras.camera_to_worlds[:, :3, 2].float()


def write_for_pipeline(pipeline: Any, path: Path, step: Optional[int] = None) -> Optional[Path]:
    """:func:`write_medium_report` for a trainer's or ``eval_setup``'s pipeline; ``None`` (nothing
    written) when its model has no medium (not a ``SeathruModel``)."""
    model = getattr(pipeline, "module", pipeline).model
    if not hasattr(model, "medium_field"):
        return None
    datamanager = pipeline.datamanager
    dataparser_config = getattr(getattr(datamanager, "dataparser", None), "config", None)
    data = getattr(dataparser_config, "data", None) or getattr(datamanager.config, "data", None)
    dataset = getattr(datamanager, "train_dataset", None)
    axes = optical_axes(dataset.cameras) if dataset is not None else None
    return write_medium_report(model, path, data, step, axes)


@dataclass
class MediumCommand:
    """Write the learned medium of a trained run as ``medium.json`` beside its ``config.yml``, and print it in one line."""

    load_config: Path
    """The run's ``config.yml``."""
    output_path: Optional[Path] = None
    """Where to write the JSON (default: ``medium.json`` beside ``config.yml``)."""

    def main(self) -> int:
        if not self.load_config.is_file():
            print(f"seathru-medium: {self.load_config}: no such file (give a run's config.yml)", file=sys.stderr)
            return 2
        from nerfstudio.utils.eval_utils import eval_setup

        try:
            _, pipeline, checkpoint, step = eval_setup(self.load_config, test_mode="test")
        except (OSError, ValueError, KeyError, RuntimeError) as error:
            print(f"seathru-medium: {self.load_config}: cannot load the run: {error}", file=sys.stderr)
            return 1
        output = self.output_path or self.load_config.parent / REPORT_NAME
        written = write_for_pipeline(pipeline, output, step)
        if written is None:
            print(f"seathru-medium: {self.load_config}: the model has no medium (not a seathru-nerf run)", file=sys.stderr)
            return 1
        report = json.loads(written.read_text())
        print(report["summary"])
        print(f"wrote {written}")
        return 0


def entrypoint() -> None:
    """``seathru-medium``."""
    import tyro

    from seathru_nerfstudio.quiet import silence_upstream_warnings

    silence_upstream_warnings()
    raise SystemExit(tyro.cli(MediumCommand).main())


if __name__ == "__main__":
    entrypoint()
