"""Sparse SfM depth maps for a dataset that has a COLMAP model but no depth maps.

The method reads everything it takes from structure from motion through the sparse depth maps
(nerfstudio's ``depth_file_path``): the near and far bounds, the range spread, the observation
table of the medium fit and the depth loss. ``seathru-process-data`` writes them; the published
SeaThru-NeRF layout (``sparse/0``) and nerfstudio's ``ns-process-data`` (``colmap/sparse/0``, depth
maps only on request) do not. For those, this module makes the same maps from the COLMAP model's
tracks with nerfstudio's own ``create_sfm_depth``, into a cache outside the dataset (the user's
data is never written to), so that every data path gives the method the same SfM.

The model's scale is arbitrary, and a 16-bit map holds z-depth × factor up to 65535: the factor puts
the 99th percentile of the observed z-depths at half that range, as ``seathru-process-data``'s
gauge does (:func:`seathru_nerfstudio.data.sfm_outputs.normalise_gauge`).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

COLMAP_MODEL_CANDIDATES = (Path("colmap/sparse/0"), Path("sparse/0"), Path("sparse"))
"""Where ``ns-process-data`` and the published layout keep the COLMAP model, relative to the dataset."""
MODEL_FILES = ("cameras", "images", "points3D")


def find_colmap_model(folder: Path) -> Optional[Path]:
    """The first folder of :data:`COLMAP_MODEL_CANDIDATES` under ``folder`` that holds a binary COLMAP
    model (what nerfstudio's ``create_sfm_depth`` reads), or ``folder`` itself if it is one; ``None``
    if there is none."""
    for candidate in (Path("."), *COLMAP_MODEL_CANDIDATES):
        model = folder / candidate
        if all((model / f"{name}.bin").is_file() for name in MODEL_FILES):
            return model
    return None


def cache_root() -> Path:
    """``$SEATHRU_CACHE`` or ``$XDG_CACHE_HOME/seathru-nerfstudio`` (``~/.cache/seathru-nerfstudio``)."""
    if os.environ.get("SEATHRU_CACHE"):
        return Path(os.environ["SEATHRU_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "seathru-nerfstudio"


def _digest(model: Path) -> str:
    sha = hashlib.sha1()
    for path in sorted(p for p in model.iterdir() if p.stem in MODEL_FILES):
        sha.update(path.name.encode())
        sha.update(path.read_bytes())
    return sha.hexdigest()[:16]


def depth_factor(model: Path) -> float:
    """The uint16 factor (map value per COLMAP unit) that puts the 99th percentile of the model's
    observed z-depths at half of 65535."""
    import pycolmap

    from seathru_nerfstudio.data.sfm_outputs import GAUGE_DEPTH_QUANTILE, observed_depths

    depths = observed_depths(pycolmap.Reconstruction(str(model)))
    depths = depths[np.isfinite(depths) & (depths > 0)]
    if depths.size == 0:
        raise ValueError(f"{model}: the COLMAP model has no 3D points seen in front of a camera")
    return 0.5 * 65535 / float(np.quantile(depths, GAUGE_DEPTH_QUANTILE))


def sparse_depth_maps(model: Path, image_names: Sequence[str]) -> Tuple[List[Path], float]:
    """Depth maps (16-bit PNG, z-depth × factor, 0 = no point) of the model's tracks for the images
    named (file names, in that order), made once and cached; and the depth unit (COLMAP units per
    map value, nerfstudio's ``depth_unit_scale_factor``). An image the model did not register gets
    an empty map: the method then knows nothing of its depth, as with a missing SfM point."""
    from nerfstudio.process_data.colmap_utils import create_sfm_depth
    import pycolmap

    factor = depth_factor(model)
    folder = cache_root() / "sfm-depth" / f"{_digest(model)}-{factor:.6g}"
    if not (folder / "done").is_file():
        folder.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".partial-", dir=folder.parent))
        try:
            by_id = create_sfm_depth(
                recon_dir=model, output_dir=staging, verbose=False, depth_scale_to_integer_factor=factor, max_depth=65535 / factor
            )
            reconstruction = pycolmap.Reconstruction(str(model))
            names: Dict[str, Path] = {reconstruction.images[i].name: Path(p) for i, p in by_id.items()}
            index = "\n".join(f"{name}\t{Path(p).name}" for name, p in sorted(names.items()))
            (staging / "index.tsv").write_text(index + "\n")
            (staging / "done").write_text("")
            os.replace(staging, folder) if not folder.exists() else shutil.rmtree(staging)
        finally:
            if staging.exists():
                shutil.rmtree(staging, ignore_errors=True)
    index = dict(line.split("\t") for line in (folder / "index.tsv").read_text().splitlines() if line)
    paths = []
    for name in image_names:
        stem = Path(name).name
        match = index.get(name) or next((file for key, file in index.items() if Path(key).name == stem), None)
        paths.append(folder / match if match else _empty_map(folder))
    return paths, 1.0 / factor


def _empty_map(folder: Path) -> Path:
    """A 1×1 map of 0 (no depth), resized by the reader to any image size."""
    import cv2

    path = folder / "empty.png"
    if not path.is_file():
        cv2.imwrite(str(path), np.zeros((1, 1), dtype=np.uint16))
    return path
