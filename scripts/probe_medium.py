"""What the SfM observations of a scene tell about its medium, before any training (seconds of CPU).

For a scene with ground truth (``seathru-synth`` or ``seathru-pathtrace``), read as training reads
it (``nerfstudio-data``: poses, sparse depths, the observation table), and print per channel:

* the truth: ``beta_D`` and the best-fit ``beta_B``, ``B_inf`` of ``ground_truth/medium.json``;
* the medium fit across views (:func:`~seathru_nerfstudio.medium_fit.fit_densities`) under the true
  veiling light, with its standard errors (what ``medium_fit_step`` would do with a perfect veil);
* the dark envelope of the whole scene (:mod:`~seathru_nerfstudio.medium_envelope`), with the veil
  fitted and with the true veil held;
* the backscatter share of the observed colour that each implies at the observations' ranges;
* how the fit's ``beta_B`` follows the veil it is given: the fit under the true veil scaled by
  0.8-1.2, with its residual (how little the observations prefer one veil over another).

    .venv/bin/python scripts/probe_medium.py outputs/pathtraced/coastal [more scenes]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch


def show(values) -> str:
    return " ".join(f"{float(v):7.3f}" for v in values)


def probe(scene: Path) -> None:
    from seathru_nerfstudio.data.nerfstudio_data import SeathruNerfstudioDataParserConfig
    from seathru_nerfstudio.medium_envelope import dark_envelope, fit_envelope
    from seathru_nerfstudio.medium_fit import fit_densities
    from seathru_nerfstudio.metadata_keys import RANGE_SPREAD_KEY, SFM_OBSERVATIONS_KEY

    outputs = SeathruNerfstudioDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    table = outputs.metadata[SFM_OBSERVATIONS_KEY]
    spread = outputs.metadata[RANGE_SPREAD_KEY]
    truth = json.loads((scene / "ground_truth" / "medium.json").read_text())
    print(f"\n== {scene}: {table.num_points} points, {table.num_observations} observations; {spread.summary()}")
    print(f"truth      beta_D {show(truth['beta_D'])}   beta_B {show(truth['beta_B'])}   B_inf {show(truth['B_inf'])}")
    veil = torch.tensor(truth["B_inf"], dtype=torch.float64)
    start = torch.full((3,), 0.5, dtype=torch.float64)
    fit = fit_densities(torch.from_numpy(table.ranges), torch.from_numpy(table.colours), veil, start, start)
    print(
        f"fit, true veil  beta_D {show(fit.attenuation)}   beta_B {show(fit.backscatter)}   "
        f"se(ln beta_D) {show(fit.attenuation_log_error)}"
    )
    observed = np.isfinite(table.ranges)
    ranges, colours = table.ranges[observed], table.colours[observed]
    centres, dark = dark_envelope(ranges, colours)
    mean_colour = colours.mean(axis=0)
    for label, held in (("envelope", None), ("envelope, true veil", truth["B_inf"])):
        envelope = fit_envelope(centres, dark, held)
        share = envelope.backscatter(ranges).mean(axis=0) / np.maximum(mean_colour, 1e-9)
        print(
            f"{label:20s} B_inf {show(envelope.veil)}   beta_B {show(envelope.beta_B)}   "
            f"backscatter share {show(share)}"
        )
    for scale in (0.8, 0.9, 1.1, 1.2):
        scaled = fit_densities(torch.from_numpy(table.ranges), torch.from_numpy(table.colours), veil * scale, start, start)
        error = scaled.backscatter.numpy() / np.asarray(truth["beta_B"]) - 1
        print(
            f"fit, veil x{scale:.1f}  beta_B error {show(100 * error)} %   residual / true veil's "
            f"{scaled.residual / fit.residual:.4f}"
        )
    true_share = (np.asarray(truth["B_inf"]) * -np.expm1(-np.asarray(truth["beta_B"]) * ranges[:, None])).mean(axis=0)
    print(f"true backscatter share {show(true_share / np.maximum(mean_colour, 1e-9))}; ranges {np.percentile(ranges, [5, 50, 95]).round(2)}")


if __name__ == "__main__":
    for path in sys.argv[1:]:
        probe(Path(path))
