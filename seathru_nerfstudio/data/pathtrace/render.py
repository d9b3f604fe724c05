"""Rendering one view of a path-traced scene with Mitsuba 3: the in-medium image, the SeaThru
``J`` term, the medium-free image, and the geometric ground truth (range, z-depth, object ids).

Mitsuba is imported here only (it is the optional ``pathtrace`` extra). Its CPU variants:
``llvm_ad_rgb`` (vectorised, JIT-compiled by libLLVM, many times faster) when a recent libLLVM
is found, else ``scalar_rgb`` (always works). Mitsuba's JIT needs LLVM >= :data:`MIN_LLVM`; an
older one aborts the process inside the compiler, so it is never picked.
"""

from __future__ import annotations

import gc
import glob
import os
import re
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Literal, Optional

import numpy as np
import numpy.typing as npt

from seathru_nerfstudio.data.pathtrace.presets import Preset
from seathru_nerfstudio.data.pathtrace.scene import (
    MODES,
    Layout,
    Mode,
    medium_dict,
    scene_dict,
    sensor_dict,
    write_meshes,
)
from seathru_nerfstudio.data.synthetic.cameras import intrinsics, pixel_rays

Variant = Literal["auto", "llvm_ad_rgb", "scalar_rgb"]
MIN_LLVM = 19
"""Oldest libLLVM used for ``llvm_ad_rgb`` (Dr.Jit's x86 code needs a recent instruction
selector: LLVM 14 and 15 abort on ``fminimum``; 19 is verified)."""
LLVM_GLOBS = ("/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/lib64/libLLVM*.so*")
OPEN_WATER_ID = -1


class PathtraceError(ValueError):
    """The options cannot be rendered (unknown preset, missing Mitsuba, bad sizes)."""


def find_libllvm() -> Optional[str]:
    """The newest libLLVM shared library with major version >= :data:`MIN_LLVM`, or None."""
    found = []
    for pattern in LLVM_GLOBS:
        for path in glob.glob(pattern):
            match = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
            if match and int(match.group(1)) >= MIN_LLVM:
                found.append((int(match.group(1)), path))
    return max(found)[1] if found else None


def load_mitsuba(variant: Variant = "auto") -> Any:
    """Import Mitsuba and set its variant; ``auto``: ``llvm_ad_rgb`` when :func:`find_libllvm`
    finds a library (or ``DRJIT_LIBLLVM_PATH`` names one), else ``scalar_rgb``."""
    try:
        import mitsuba as mi
    except ImportError as error:
        raise PathtraceError(f"Mitsuba 3 is not installed ({error}); install the extra: pip install -e '.[pathtrace]'") from None
    if variant == "auto":
        library = os.environ.get("DRJIT_LIBLLVM_PATH") or find_libllvm()
        variant = "llvm_ad_rgb" if library else "scalar_rgb"
        if library:
            os.environ.setdefault("DRJIT_LIBLLVM_PATH", library)  # read by Dr.Jit's first LLVM use
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


@dataclass
class ViewRender:
    """One view; images are exposure-scaled linear RGB (H, W, 3) float32 (not yet clipped)."""

    image: npt.NDArray[np.float32]
    clean: npt.NDArray[np.float32]
    """The J term; 0 on open water (as ``seathru-synth`` writes)."""
    dry: npt.NDArray[np.float32]
    range: npt.NDArray[np.float32]
    """(H, W) metres from the camera centre along the pixel-centre ray; inf on open water / sky."""
    z_depth: npt.NDArray[np.float32]
    """(H, W) metres along the optical axis; inf where ``range`` is."""
    ids: npt.NDArray[np.int16]
    """(H, W) 0 = seabed / ground, i + 1 = object i, -1 = open water / sky."""
    seconds: Dict[str, float] = field(default_factory=dict)


class Renderer:
    """Mitsuba scenes of one layout (one per mode), loaded once; :meth:`render` draws one view."""

    def __init__(self, layout: Layout, preset: Preset, width: int, height: int, spp: int, max_depth: int = 24, variant: Variant = "auto"):
        self.mi = load_mitsuba(variant)
        self.layout, self.preset = layout, preset
        self.width, self.height, self.spp = width, height, spp
        self._folder = tempfile.TemporaryDirectory(prefix="seathru-pathtrace-")
        meshes = write_meshes(self.mi, layout, preset, Path(self._folder.name))
        self.medium = self.mi.load_dict(medium_dict(preset)) if preset.medium != "none" else None
        modes = MODES if self.medium is not None else ("dry",)
        self.scenes = {mode: self.mi.load_dict(scene_dict(self.mi, layout, preset, meshes, mode, self.medium, max_depth)) for mode in modes}
        self.K = intrinsics(width, height)

    def close(self) -> None:
        """Free the Mitsuba scenes and medium now (with their meshes' folder). Left to the garbage
        collector, Dr.Jit objects can be destroyed in the middle of a later renderer's render,
        which then finds a freed pointer in the JIT registry ("pointer is not registered")."""
        self.scenes.clear()
        self.medium = None
        gc.collect()
        self._folder.cleanup()

    def render_mode(self, mode: Mode, c2w: npt.NDArray[np.float64], seed: int) -> npt.NDArray[np.float32]:
        """Exposure x radiance (H, W, 3) of ``mode`` from pose ``c2w`` with sampler ``seed``."""
        scene = self.scenes.get(mode, self.scenes["dry"])
        medium = self.medium if mode == "medium" else None
        sensor = self.mi.load_dict(sensor_dict(self.mi, c2w, self.width, self.height, self.spp, medium))
        image = np.array(self.mi.render(scene, sensor=sensor, seed=seed), dtype=np.float32)[..., :3]
        return image * np.float32(self.preset.exposure)

    def render(self, c2w: npt.NDArray[np.float64], seed: int) -> ViewRender:
        """All renders and the ground truth of one view. Sampler seeds: ``3 seed + mode``."""
        seconds = {}
        images = {}
        for index, mode in enumerate(MODES):
            if mode in self.scenes or mode == "dry":
                start = time.perf_counter()
                images[mode] = self.render_mode(mode, c2w, 3 * seed + index)
                seconds[mode] = time.perf_counter() - start
        for mode in MODES:  # no medium: all three are the same picture
            images.setdefault(mode, images["dry"])
        distance, ids = self.cast(c2w)
        direction = pixel_rays(c2w, self.K, *self._pixel_grid())
        z_depth = distance * (direction @ -c2w[:3, 2]).astype(np.float32)
        clean = np.where((ids == OPEN_WATER_ID)[..., None], np.float32(0.0), images["clean"])
        return ViewRender(images["medium"], clean, images["dry"], distance, z_depth, ids, seconds)

    def _pixel_grid(self):
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        return u, v

    def cast(self, c2w: npt.NDArray[np.float64]):
        """Range (H, W) float32 and object ids (H, W) int16 of the pixel-centre rays, from the
        medium-free scene's geometry (the medium's box is not an object)."""
        mi = self.mi
        scene = self.scenes["dry"]
        directions = pixel_rays(c2w, self.K, *self._pixel_grid()).reshape(-1, 3)
        origin = c2w[:3, 3]
        index_of = {shape.id(): _shape_index(shape.id()) for shape in scene.shapes()}
        if mi.variant().startswith("scalar"):
            t = np.full(len(directions), np.inf)
            ids = np.full(len(directions), OPEN_WATER_ID, dtype=np.int16)
            for k, d in enumerate(directions):
                si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(*d)))
                if si.is_valid():
                    t[k], ids[k] = si.t, index_of[si.shape.id()]
        else:
            import drjit as dr

            ray = mi.Ray3f(
                mi.Point3f(*(np.full(len(directions), c, dtype=np.float32) for c in origin)),
                mi.Vector3f(*(directions[:, c].astype(np.float32) for c in range(3))),
            )
            si = scene.ray_intersect(ray)
            valid = np.array(si.is_valid())
            t = np.where(valid, np.array(si.t, dtype=np.float64), np.inf)
            pointers = np.array(dr.reinterpret_array(mi.UInt32, si.shape))
            by_pointer = {int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s)))[0]): index_of[s.id()] for s in scene.shapes()}
            ids = np.array([by_pointer.get(int(p), OPEN_WATER_ID) for p in pointers], dtype=np.int16)
            ids[~valid] = OPEN_WATER_ID
        shape = (self.height, self.width)
        return t.astype(np.float32).reshape(shape), ids.reshape(shape)


def _shape_index(name: str) -> int:
    """0 for the seabed ("bed"), i + 1 for "object_<i>"."""
    return int(name.split("_")[1]) + 1 if name.startswith("object_") else 0
