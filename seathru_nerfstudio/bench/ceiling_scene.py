"""The ceiling of one scene with ground truth (:mod:`seathru_nerfstudio.bench.ceiling`): fit the
medium on the training views, invert the held-out views, score them with the code that scores
every method (:func:`seathru_nerfstudio.metrics.clean_psnrs`).

The views and their ground truth are those the benchmark's runs see: the splits and the files
of ``nerfstudio-data`` (this package's parser, its defaults), the medium from
``ground_truth/medium.json``. Ranges are read in world units (metres), as the densities are.

Two variants:

* ``ceiling``: β_D the truth's, β_B and B∞ the least-squares best fit (:func:`ceiling.fit_backscatter`);
  the reference for a method's β_B and B∞, whose true values need not be those of the formation
  model when the images were not drawn with it (a path-traced scene);
* ``ceiling_all_fitted``: β_D fitted too (:func:`ceiling.fit_medium`), for information.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

from seathru_nerfstudio import metrics
from seathru_nerfstudio.bench import ceiling, scoring

VARIANTS: Dict[str, str] = {
    "ceiling": "ceiling: true z, true β_D, fitted β_B, B∞",
    "ceiling_all_fitted": "ceiling: true z, fitted β_D, β_B, B∞",
}
"""Variant key -> the label of its row in the tables."""


class NoGroundTruth(ValueError):
    """The scene has no ground truth to compute a ceiling from (a real capture): not an error
    for the benchmark, which then reports no ceiling."""


def read_medium(scene: Path) -> Dict[str, List[float]]:
    """``ground_truth/medium.json``'s beta_D, beta_B, B_inf (1/m, 1/m, linear; three values each)."""
    path = scene / "ground_truth" / "medium.json"
    if not path.is_file():
        raise NoGroundTruth(f"{path}: no such file (the scene has no true medium)")
    try:
        data = json.loads(path.read_text())
        medium = {key: [float(v) for v in data[key]] for key in scoring.MEDIUM_KEYS}
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{path}: not a medium (needs three numbers each for {', '.join(scoring.MEDIUM_KEYS)}): {error!r}") from error
    bad = [key for key, values in medium.items() if len(values) != 3 or not all(np.isfinite(values))]
    if bad:
        raise ValueError(f"{path}: {', '.join(bad)} must be three finite numbers")
    return medium


def _split(scene: Path, split: str) -> List[Tuple[str, Path, Path, Path]]:
    """(name, image, clean, range) of each view of a split, as the benchmark's parser lists them."""
    from seathru_nerfstudio.data.ground_truth import GT_CLEAN_FILENAMES, GT_DEPTH_FILENAMES
    from seathru_nerfstudio.data.nerfstudio_data import SeathruNerfstudioDataParserConfig

    parser = SeathruNerfstudioDataParserConfig(data=scene, sfm_observations=False).setup()
    outputs = parser.get_dataparser_outputs(split=split)
    clean, ranges = outputs.metadata.get(GT_CLEAN_FILENAMES), outputs.metadata.get(GT_DEPTH_FILENAMES)
    if not clean or not ranges:
        raise NoGroundTruth(f"{scene / 'transforms.json'}: its frames declare no gt_clean_file_path and gt_depth_file_path")
    return [(Path(i).name, Path(i), Path(c), Path(r)) for i, c, r in zip(outputs.image_filenames, clean, ranges)]


def _load(views) -> Tuple[List[np.ndarray], List[np.ndarray], List[np.ndarray]]:
    from seathru_nerfstudio.data.linear_images import read_linear_image, read_range_map

    images, cleans, ranges = [], [], []
    for _, image, clean, depth in views:
        images.append(read_linear_image(image)[..., :3].astype(np.float64))
        cleans.append(read_linear_image(clean)[..., :3].astype(np.float64))
        ranges.append(read_range_map(depth).astype(np.float64))
        if not (images[-1].shape == cleans[-1].shape and images[-1].shape[:2] == ranges[-1].shape):
            raise ValueError(
                f"{image}: {images[-1].shape[:2]} pixels, its clean image {cleans[-1].shape[:2]} and range {ranges[-1].shape}: they must match"
            )
    return images, cleans, ranges


def _stack(images: List[np.ndarray], cleans: List[np.ndarray], ranges: List[np.ndarray]):
    """Every view's object pixels as one ``(N, 3), (N, 3), (N,)`` set (open water left out)."""
    objects = [np.isfinite(z) for z in ranges]
    return (
        np.concatenate([i[m] for i, m in zip(images, objects)]),
        np.concatenate([c[m] for c, m in zip(cleans, objects)]),
        np.concatenate([z[m] for z, m in zip(ranges, objects)]),
    )


def score_inversion(
    medium: ceiling.MediumFit, names: List[str], images: List[np.ndarray], cleans: List[np.ndarray], ranges: List[np.ndarray]
) -> Dict[str, Any]:
    """Invert each view with ``medium`` and its true range, and score Ĵ against the true J with
    :func:`metrics.clean_psnrs` (Ĵ clipped to [0, 1] there, as every method's clean image is):
    per-view scores, their mean over views, and the number of capped gains (:func:`ceiling.invert`)."""
    per_view, capped = [], 0
    for name, image, clean, z in zip(names, images, cleans, ranges):
        J_hat, n = ceiling.invert(image, z, np.array(medium.beta_D), np.array(medium.beta_B), np.array(medium.B_inf))
        capped += n
        scores = metrics.clean_psnrs(torch.from_numpy(J_hat), torch.from_numpy(clean), torch.from_numpy(z)[..., None])
        per_view.append({"view": name, **scores})
    numeric = [{k: v for k, v in view.items() if k != "view"} for view in per_view]
    return {"metrics": scoring.mean_metrics(numeric), "per_view": per_view, "capped_gains": capped}


def scene_registration(scene: Path) -> Optional[Dict[str, Any]]:
    """How the scene's poses were made, as ``seathru-pathtrace`` records it in ``scene.json``
    (``registration``: images registered, and for SfM poses the median rotation error in degrees
    and the camera centres' rms residual in metres after a similarity to the truth); ``None``
    for a scene without that record. A benchmark on poses that are wrong measures the SfM."""
    try:
        record = json.loads((scene / "scene.json").read_text())
    except (OSError, json.JSONDecodeError):
        return None
    registration = record.get("registration") if isinstance(record, dict) else None
    return registration if isinstance(registration, dict) else None


def registration_line(registration: Optional[Dict[str, Any]]) -> Optional[str]:
    """One line on the poses of a scene (:func:`scene_registration`), or ``None`` without a record."""
    if not registration:
        return None
    if registration.get("poses") != "sfm":
        return f"poses: {registration.get('poses', 'unknown')} (not structure from motion)"
    if "failed" in registration:
        return f"poses: structure from motion failed ({registration['failed']})"
    line = f"poses: structure from motion, {registration.get('registered')}/{registration.get('total')} views registered"
    if "rotation_error_deg_median" in registration:
        line += (
            f", {registration['rotation_error_deg_median']:.2f}° median rotation error and "
            f"{registration['alignment_residual_rms_m']:.3f} m rms camera-centre residual after a similarity to the truth"
        )
    return line


def scene_ceiling(scene: Path, name: Optional[str] = None) -> Dict[str, Any]:
    """The ceiling record of a scene (see the module docstring): the truth, both fits, their
    errors, and each variant's held-out J scores. Raises :class:`NoGroundTruth` for a scene
    without ground truth and ``ValueError`` (naming the file) for unreadable ground truth."""
    scene = Path(scene).expanduser().resolve()
    truth = read_medium(scene)
    train, held_out = _split(scene, "train"), _split(scene, "val")
    fit_images, fit_cleans, fit_ranges = _load(train)
    fit_split = "train"
    if not any(np.isfinite(z).any() for z in fit_ranges):
        raise ValueError(f"{scene}: no training view sees an object (every true range is inf): nothing to fit the medium on")
    I, J, z = _stack(fit_images, fit_cleans, fit_ranges)
    fit = ceiling.fit_backscatter(I, J, z, np.array(truth["beta_D"]))
    fit_all = ceiling.fit_medium(I, J, z, start=fit)
    reference = {"beta_D": truth["beta_D"], "beta_B": list(fit.beta_B), "B_inf": list(fit.B_inf)}

    images, cleans, ranges = _load(held_out)
    names = [view[0] for view in held_out]
    variants = {}
    for key, medium in (("ceiling", fit), ("ceiling_all_fitted", fit_all)):
        variants[key] = {"label": VARIANTS[key], "medium": medium.as_dict(), **score_inversion(medium, names, images, cleans, ranges)}
        variants[key]["medium_error"] = scoring.medium_error(medium.as_dict(), reference)
    return {
        "scene": name or scene.name,
        "scene_path": str(scene),
        "truth": truth,
        "reference": reference,
        "fit_split": fit_split,
        "fit_views": [view[0] for view in train],
        "held_out_views": names,
        "fit": fit.as_dict(),
        "fit_all": fit_all.as_dict(),
        "fit_vs_truth": scoring.medium_error(fit.as_dict(), truth),
        "registration": scene_registration(scene),
        "variants": variants,
        "note": "Ĵ = (I − B∞(1 − e^{−β_B z})) e^{β_D z} with the true range z; clipped to [0, 1] only for the PSNR; "
        "medium fits by least squares over the training views' object pixels (J and z true); β_B, B∞ of methods "
        "are compared with the 'reference' (the fit), β_D with the truth.",
    }
