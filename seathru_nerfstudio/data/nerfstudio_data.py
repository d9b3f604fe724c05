"""nerfstudio's own ``nerfstudio-data`` parser, telling the model its scale and near bound.

* The model reports the medium per metre (world unit), not per scene unit, and takes an
  oracle medium in 1/m. Both need the dataparser scale (scene units per world unit), which
  nerfstudio keeps in ``DataparserOutputs.dataparser_scale`` but does not hand to the model;
  this parser copies it into ``metadata["dataparser_scale"]``, which the model receives.
* When the frames have sparse SfM depths (``depth_file_path``), they bound where objects
  are, as LLFF's ``poses_bounds`` do for ``seathru-data``: ``metadata["near_plane"]`` and
  ``metadata["far_plane"]`` (scene units). In water this matters: an object field allowed
  right in front of the lens can explain the whole image as a dark screen veiled by
  backscatter, and one allowed out to nerfacto's 1000 units starts as an opaque wall behind
  the open water, which no gradient removes once the water hides it. The renderer's
  closed-form water before the near and after the far bound keeps the medium unclipped.
* Ground truth that the frames declare (``gt_depth_file_path``, ``gt_clean_file_path``, see
  :mod:`seathru_nerfstudio.data.ground_truth`) goes into ``metadata`` as paths that follow
  ``image_filenames``, for ``LinearImageDataset`` to load.
* On the training split, one log line says how much the SfM points' range varies between
  views (:mod:`seathru_nerfstudio.data.range_diversity`): the only thing that determines the
  attenuation, and small for a flat forward-facing rig.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Sequence, Type

import cv2
import numpy as np
import torch

from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from nerfstudio.data.utils.data_utils import get_depth_image_from_path
from nerfstudio.utils.io import load_from_json
from nerfstudio.utils.rich_utils import CONSOLE
from seathru_nerfstudio.data.colmap_depths import COLMAP_MODEL_CANDIDATES, find_colmap_model, sparse_depth_maps
from seathru_nerfstudio.data.ground_truth import FRAME_FIELDS, legacy_paths
from seathru_nerfstudio.data.input_checks import check_images, load_transforms
from seathru_nerfstudio.data.linear_images import read_linear_image
from seathru_nerfstudio.data.range_diversity import RangeSpread, range_spread
from seathru_nerfstudio.data.sfm_observations import SfmObservations, sfm_observations
from seathru_nerfstudio.input_errors import InputError
from seathru_nerfstudio.metadata_keys import EXTENT_KEY, RANGE_SPREAD_KEY, SCALE_KEY, SFM_OBSERVATIONS_KEY, VERTICAL_KEY
from seathru_nerfstudio.vertical import scene_vertical

NEAR_PERCENTILE = 0.1
"""Per image, the near bound is this percentile of its SfM depths (LLFF's choice), so that a
stray point does not set it; the far bound the opposite percentile."""


@dataclass
class SeathruNerfstudioDataParserConfig(NerfstudioDataParserConfig):
    """``nerfstudio-data`` (transforms.json), with the scale in the model's metadata."""

    _target: Type = field(default_factory=lambda: SeathruNerfstudio)
    sfm_observations: bool = True
    """Also tabulate the SfM points' ranges and colours in every training view that sees them
    (:mod:`seathru_nerfstudio.data.sfm_observations`), for the model's ``medium_fit_step``.
    Reads every training image once more at start-up, one at a time (about 1 s on the demos)."""


class GroundTruthError(InputError):
    """The frames declare ground truth for some frames only, or name files that do not exist."""


class SeathruNerfstudio(Nerfstudio):
    """nerfstudio's parser; the scale, SfM bounds and declared ground truth added to ``metadata``."""

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        load_transforms(self.config.data)  # its frames and the files they name, checked before nerfstudio reads them
        outputs = super()._generate_dataparser_outputs(split, **kwargs)
        check_images(outputs.image_filenames, outputs.cameras.height.flatten().tolist(), outputs.cameras.width.flatten().tolist())
        outputs.metadata.update(self._ground_truth([Path(p) for p in outputs.image_filenames]))
        scale = float(outputs.dataparser_scale)
        outputs.metadata[SCALE_KEY] = scale
        outputs.metadata[VERTICAL_KEY] = scene_vertical(outputs.cameras.camera_to_worlds).tolist()
        if not outputs.metadata.get("depth_filenames"):
            transforms = self.config.data if self.config.data.suffix == ".json" else self.config.data / "transforms.json"
            depths_from_colmap(outputs, transforms.parent)
        add_sfm_metadata(outputs, split, self.config.sfm_observations)
        return outputs

    def _ground_truth(self, image_filenames: List[Path]) -> Dict[str, List[Path]]:
        """The ground-truth files the frames declare, in ``image_filenames`` order (metadata key ->
        paths); for a ``seathru-synth`` scene older than these fields, its fixed layout."""
        transforms = self.config.data if self.config.data.suffix == ".json" else self.config.data / "transforms.json"
        frames = load_from_json(transforms)["frames"]
        by_image = {self._get_fname(Path(frame["file_path"]), transforms.parent): frame for frame in frames}
        found: Dict[str, List[Path]] = {}
        for key, name in FRAME_FIELDS.items():
            declared = sum(name in frame for frame in frames)
            if declared == 0:
                continue
            if declared < len(frames):
                raise GroundTruthError(
                    f"{transforms}: {declared} of {len(frames)} frames have {name!r}; give it for every frame or for none"
                )
            found[key] = [transforms.parent / by_image[image][name] for image in image_filenames]
            missing = [str(path) for path in found[key] if not path.is_file()]
            if missing:
                raise GroundTruthError(f"{transforms}: {name} names {len(missing)} missing file(s): {', '.join(missing[:3])}")
        if found:
            return found
        legacy = legacy_paths(transforms.parent, image_filenames)
        if legacy:
            warnings.warn(
                f"{transforms} declares no ground truth; using the files in its ground_truth/ folder (a seathru-synth "
                "scene written before frames named them: write it again to declare them)"
            )
        return legacy


def depths_from_colmap(outputs: DataparserOutputs, folder: Path) -> None:
    """Give ``outputs`` sparse depth maps made from the COLMAP model under ``folder``
    (:mod:`seathru_nerfstudio.data.colmap_depths`), or say in one line what is lost without one."""
    model = find_colmap_model(folder)
    if model is None:
        CONSOLE.print(
            f"[bold yellow]seathru: {folder} has no SfM depth maps (depth_file_path) and no COLMAP model "
            f"({', '.join(str(p) for p in COLMAP_MODEL_CANDIDATES)}): training without SfM bounds, depth loss or medium fit"
        )
        return
    names = [Path(p).name for p in outputs.image_filenames]
    paths, unit = sparse_depth_maps(model, names)
    outputs.metadata["depth_filenames"] = paths
    outputs.metadata["depth_unit_scale_factor"] = unit
    CONSOLE.print(f"seathru: sparse depths from the tracks of the COLMAP model {model} (cached in {paths[0].parent})")


def add_sfm_metadata(outputs: DataparserOutputs, split: str, observations: bool, bounds: bool = True) -> None:
    """From the sparse depth maps (``depth_filenames``, if any): the SfM near and far bounds and the
    frustum extent (``bounds``), and on the training split the range spread and (``observations``)
    the observation table of the medium fit."""
    depth_files = outputs.metadata.get("depth_filenames")
    if not depth_files:
        return
    scale = float(outputs.dataparser_scale)
    unit = float(outputs.metadata["depth_unit_scale_factor"])
    depths = read_sparse_depths(depth_files, outputs.cameras.height, outputs.cameras.width)
    near_far = sfm_bounds(depths)
    if bounds and near_far is not None:
        outputs.metadata["near_plane"] = near_far[0] * unit * scale
        outputs.metadata["far_plane"] = near_far[1] * unit * scale
        outputs.metadata[EXTENT_KEY] = frustum_extent(outputs.cameras, outputs.metadata["far_plane"])
    if split != "train":
        return
    spread = sfm_range_spread([depth * unit for depth in depths], outputs.cameras, scale)
    outputs.metadata[RANGE_SPREAD_KEY] = spread
    CONSOLE.print(spread.summary())
    if observations:
        table = observations_of([depth * unit for depth in depths], outputs, scale)
        outputs.metadata[SFM_OBSERVATIONS_KEY] = table
        CONSOLE.print(
            f"SfM observations: {table.num_points} points seen {table.num_observations} times in all (for medium_fit_step)"
        )


def read_sparse_depths(depth_files, heights, widths) -> List[np.ndarray]:
    """The sparse depth maps, (H, W) each, in file units (z-depth, 0 = unknown), read once for
    both the bounds and the range spread."""
    return [
        get_depth_image_from_path(Path(path), int(height), int(width), scale_factor=1.0).numpy()[..., 0]
        for path, height, width in zip(depth_files, heights.flatten().tolist(), widths.flatten().tolist())
    ]


def sfm_bounds(depths: List[np.ndarray]) -> tuple[float, float] | None:
    """(near, far): the smallest per-image ``NEAR_PERCENTILE`` and the largest per-image
    ``100 - NEAR_PERCENTILE`` percentile of the sparse depths, in their units (z-depth);
    ``None`` without any point."""
    nears, fars = [], []
    for depth in depths:
        known = depth[depth > 0]
        if known.size:
            nears.append(float(np.percentile(known, NEAR_PERCENTILE)))
            fars.append(float(np.percentile(known, 100.0 - NEAR_PERCENTILE)))
    return (min(nears), max(fars)) if nears else None


def frustum_extent(cameras, far_depth: float) -> float:
    """The largest ``|x|∞`` of nerfstudio's ``cameras``' view frustums cut at z-depth ``far_depth``
    (pinhole part of the model; the camera looks along its ``-z``), in the poses' units.

    ``|x|∞`` is convex and a cut frustum is the convex hull of the camera centre and its four image
    corners at ``far_depth``, so the maximum over those five points per camera is exact."""
    if not (math.isfinite(far_depth) and far_depth > 0):
        raise ValueError(f"the far depth must be finite and positive, got {far_depth}")
    flat = lambda values: values.flatten().double()  # noqa: E731
    width, height = flat(cameras.width), flat(cameras.height)
    corners_u = torch.stack([torch.zeros_like(width), width, torch.zeros_like(width), width], dim=-1)  # [N, 4]
    corners_v = torch.stack([torch.zeros_like(height), torch.zeros_like(height), height, height], dim=-1)
    x = (corners_u - flat(cameras.cx)[:, None]) / flat(cameras.fx)[:, None]
    y = -(corners_v - flat(cameras.cy)[:, None]) / flat(cameras.fy)[:, None]
    directions = torch.stack([x, y, -torch.ones_like(x)], dim=-1) * far_depth  # camera frame, [N, 4, 3]
    camera_to_worlds = cameras.camera_to_worlds.double().reshape(-1, 3, 4)
    rotation, centre = camera_to_worlds[:, :, :3], camera_to_worlds[:, :, 3]
    corners = torch.einsum("nij,nkj->nki", rotation, directions) + centre[:, None, :]
    return float(torch.cat([centre[:, None, :], corners], dim=1).abs().amax())


def world_pinholes(cameras, scene_per_world: float):
    """``(camera_to_worlds, fx, fy, cx, cy)`` of nerfstudio's ``cameras`` as float64 arrays, the
    poses scaled back to world units (scene units / ``scene_per_world``)."""
    flat = lambda values: values.flatten().double().numpy()  # noqa: E731
    camera_to_worlds = cameras.camera_to_worlds.double().numpy().copy()
    camera_to_worlds[:, :, 3] /= scene_per_world
    return camera_to_worlds, flat(cameras.fx), flat(cameras.fy), flat(cameras.cx), flat(cameras.cy)


def sfm_range_spread(world_depths: List[np.ndarray], cameras, scene_per_world: float) -> RangeSpread:
    """:func:`range_spread` of the sparse depth maps (world units) under nerfstudio's ``cameras``
    (scene units; the pinhole part of the model), in world units: the poses are scaled back to
    world units, so no depth is converted twice."""
    return range_spread(world_depths, *world_pinholes(cameras, scene_per_world))


class _ImagesAtCameraSize(Sequence):
    """The split's linear images (RGB), read when indexed and resized to the cameras' size: the
    observation table needs one at a time, and a capture's images may not fit in memory together."""

    def __init__(self, outputs: DataparserOutputs) -> None:
        self.paths = list(outputs.image_filenames)
        self.sizes = list(zip(outputs.cameras.height.flatten().tolist(), outputs.cameras.width.flatten().tolist()))

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> np.ndarray:
        height, width = self.sizes[index]
        image = read_linear_image(self.paths[index])[..., :3]
        if image.shape[:2] != (height, width):
            image = cv2.resize(image, (int(width), int(height)), interpolation=cv2.INTER_AREA)
        return image


def observations_of(world_depths: List[np.ndarray], outputs: DataparserOutputs, scene_per_world: float) -> SfmObservations:
    """:func:`sfm_observations` of the sparse depth maps (world units) and the split's images
    (resized to the cameras' size, read one at a time), under nerfstudio's cameras scaled back to world units."""
    return sfm_observations(world_depths, _ImagesAtCameraSize(outputs), *world_pinholes(outputs.cameras, scene_per_world))
