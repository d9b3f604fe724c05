"""Where the medium fit's own error comes from on a ``seathru-pathtrace`` scene (an oracle: the true
range, J and best-fit medium; seconds of CPU per scene).

The fit (:func:`~seathru_nerfstudio.medium_fit.fit_densities`) assumes one colour ``J`` per SfM point
and the constant medium's backscatter ``B∞ (1 − e^{−β_B z})`` in every view. This samples, at exactly
the pixels the observation table samples (the training split's SfM depth maps, moved to the flattest
pixel as training moves them), the image ``I``, the true ``J`` (``ground_truth/clean``), the true range
and the true backscatter ``I − J e^{−β_D z}``, and fits under the best-fit veil
(``ground_truth/medium.json``) to colours built from:

* the formation model with one ``J`` per point (its mean over the point's views): exact, a check;
* the same with each view's own sampled ``J``: what ``J``'s change between views does alone;
* one ``J`` per point with the true backscatter: what the path-traced backscatter does alone;
* the observed colours (both), with the true and with the table's ranges.

It also prints how the true backscatter at the observations compares with the best fit, by range, and
how much of it grows with each view's direct light ``J e^{−β_D z}`` times the range: the object's own light
scattered forward into the pixels around it, which a colour-against-range fit can only read as an
attenuation lower by about ``f / (1 + f z)`` (``f`` that coefficient, 1/m).

    .venv/bin/python scripts/probe_fit_error.py outputs/pathtraced/turbid [more scenes]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

RANGE_BINS_M = (0.0, 2.5, 3.5, 5.0, 8.0, 100.0)
"""Range bins (m) of the comparison with the best fit."""
MAX_LOG_RANGE_MISMATCH = 0.3
"""Observations whose sampled true range and SfM range differ by more (a factor of 1.35) are left out."""


def sampled_tables(scene: Path):
    """The observation table's samples of ``I``, ``J``, the true range and the true and best-fit
    backscatter (each a :class:`~seathru_nerfstudio.data.sfm_observations.SfmObservations`), and the truth."""
    from seathru_nerfstudio.data import nerfstudio_data
    from seathru_nerfstudio.data.linear_images import read_linear_image, read_range_map
    from seathru_nerfstudio.data.sfm_observations import at_flattest_pixels, sfm_observations

    outputs = nerfstudio_data.SeathruNerfstudioDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    truth = json.loads((scene / "ground_truth" / "medium.json").read_text())
    beta_d, beta_b, veil = (np.asarray(truth[k]) for k in ("beta_D", "beta_B", "B_inf"))
    unit = float(outputs.metadata["depth_unit_scale_factor"])
    depths = nerfstudio_data.read_sparse_depths(outputs.metadata["depth_filenames"], outputs.cameras.height, outputs.cameras.width)
    images = nerfstudio_data._ImagesAtCameraSize(outputs)
    moved = [at_flattest_pixels(np.asarray(d * unit, np.float64), images[i], 2) for i, d in enumerate(depths)]  # as training
    maps = {"I": [], "J": [], "z": [], "B_true": [], "B_fit": []}
    for i, path in enumerate(outputs.image_filenames):
        name = Path(path).stem
        image = images[i].astype(np.float64)
        clean = read_linear_image(scene / "ground_truth" / "clean" / f"{name}.png")[..., :3].astype(np.float64)
        ranges = read_range_map(scene / "ground_truth" / "depth" / f"{name}.npy").astype(np.float64)
        ranges = np.repeat(np.where(np.isfinite(ranges), ranges, 1e3)[..., None], 3, axis=-1)  # open water: far
        maps["I"].append(image)
        maps["J"].append(clean)
        maps["z"].append(ranges)
        maps["B_true"].append(image - clean * np.exp(-beta_d * ranges))
        maps["B_fit"].append(veil * -np.expm1(-beta_b * ranges))
    pinholes = nerfstudio_data.world_pinholes(outputs.cameras, float(outputs.dataparser_scale))
    tables = {key: sfm_observations(moved, values, *pinholes, flattest_within=0) for key, values in maps.items()}
    return tables, beta_d, beta_b, veil


def probe(scene: Path) -> None:
    from seathru_nerfstudio.medium_fit import fit_densities

    tables, beta_d, beta_b, veil = sampled_tables(scene)
    sampled_range = tables["z"].colours[..., 0]
    observed = np.isfinite(tables["I"].ranges)
    # a sample that straddles a silhouette against open water mixes a surface's range with the far
    # stand-in: its true range is not one surface's, and no formation model holds there
    seen = observed & (np.abs(np.log(np.where(observed, sampled_range / tables["I"].ranges, 1.0))) < MAX_LOG_RANGE_MISMATCH)
    true_range = np.where(seen, sampled_range, np.nan)
    sample = {key: np.where(seen[..., None], table.colours, np.nan) for key, table in tables.items()}
    point_clean = np.nanmean(sample["J"], axis=1, keepdims=True)
    attenuation = np.exp(-beta_d * true_range[..., None])
    several = seen.sum(axis=1) >= 2
    spread = np.nanstd(sample["J"], axis=1)[several] / np.maximum(point_clean[several, 0], 1e-6)
    print(f"\n== {scene}: {int(seen.sum())} observations ({int(observed.sum() - seen.sum())} on silhouettes left out) of "
          f"{int(several.sum())} points seen twice or more; "
          f"table range / true range, median {np.nanmedian(tables['I'].ranges / true_range):.3f}; "
          f"J's relative spread over a point's views, median {' '.join(f'{v:.3f}' for v in np.median(spread, axis=0))}")
    z = true_range[seen]
    for near, far in zip(RANGE_BINS_M, RANGE_BINS_M[1:]):
        cell = (z >= near) & (z < far)
        if cell.sum() >= 30:
            ratio = sample["B_true"][seen][cell].sum(0) / sample["B_fit"][seen][cell].sum(0)
            print(f"  true range {near:>4.1f}-{far:<5.1f} m ({int(cell.sum()):4d} observations): true / best-fit backscatter "
                  f"{' '.join(f'{r:.3f}' for r in ratio)}")
    # the object's light scattered forward into nearby pixels rides on the "backscatter" I - J e^{-beta_D z}:
    # it grows with the direct light and the range, which the fit can only read as a lower attenuation
    per_view_direct = (sample["J"] * attenuation)[seen]
    excess = (sample["B_true"] - sample["B_fit"])[seen]
    coefficients = []
    for c in range(3):
        design = np.stack([np.ones_like(z), per_view_direct[:, c] * z, -np.expm1(-beta_b[c] * z)], axis=1)
        coefficients.append(np.linalg.lstsq(design, excess[:, c], rcond=None)[0][1])
    print(f"  true - best-fit backscatter per unit of direct light and metre (forward scatter, 1/m): "
          f"{' '.join(f'{v:+.3f}' for v in coefficients)}; the fit can read beta_D lower by about that / (1 + that x range)")
    cases = (
        ("one J per point, best-fit backscatter (exact)", point_clean * attenuation + sample["B_fit"], true_range),
        ("each view's own J, best-fit backscatter", sample["J"] * attenuation + sample["B_fit"], true_range),
        ("one J per point, the true backscatter", point_clean * attenuation + sample["B_true"], true_range),
        ("observed colours, true ranges", sample["I"], true_range),
        ("observed colours, the table's ranges (training's)", sample["I"], np.where(seen, tables["I"].ranges, np.nan)),
    )
    start = torch.full((3,), 0.5, dtype=torch.float64)
    for label, colours, ranges in cases:
        fit = fit_densities(torch.from_numpy(ranges), torch.from_numpy(colours), torch.from_numpy(veil), start, start)
        print(f"  fit under the best-fit veil, {label:50s} beta_D error {' '.join(f'{v:+4.0f}' for v in 100 * (fit.attenuation.numpy() / beta_d - 1))} %"
              f"   beta_B error {' '.join(f'{v:+4.0f}' for v in 100 * (fit.backscatter.numpy() / beta_b - 1))} %")


if __name__ == "__main__":
    for path in sys.argv[1:]:
        probe(Path(path))
