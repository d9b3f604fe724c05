"""``seathru-restore``: every training and test photo rendered again, without the water.

``ns-render dataset --rendered-output-names clean_display --split train+test`` already writes
8-bit PNGs named after the inputs; it cannot write 16-bit images (linear outputs become 8-bit
colour-mapped PNGs, or ``raw-<name>`` float arrays in ``.npy.gz``). This command renders the
same cameras (the dataset's, at the training resolution) and writes, for each output named:

* a display output (``clean_display``, ``rgb_display``, ... ; :data:`viewer.DISPLAY_OUTPUTS`):
  an 8-bit sRGB PNG, as the viewer shows it: for looking at;
* a linear colour output (``clean``, ``rgb``, ``direct``, ``backscatter``, ``medium_rgb``): a
  16-bit PNG of the linear values, ``value / 65535`` (no gamma, RGB order, as
  ``seathru-process-data`` writes its inputs): for measuring.

Layout: ``<output-dir>/<output>/<the input's path below the images' common folder>.png``, e.g.
``restored/clean_display/frame_00003.png`` for ``images/frame_00003.png``. The folder appears
whole or not at all (built beside it, then renamed).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Literal, Sequence, Tuple

import numpy as np
import torch

from seathru_nerfstudio import viewer

LINEAR_COLOURS = viewer.COLOUR_OUTPUTS
"""Outputs written as 16-bit linear PNGs."""


def image_kind(name: str) -> str:
    """``"display"`` (8-bit sRGB) or ``"linear"`` (16-bit), or a ``ValueError`` naming the choices."""
    if name in viewer.DISPLAY_OUTPUTS:
        return "display"
    if name in LINEAR_COLOURS:
        return "linear"
    raise ValueError(
        f"--outputs {name}: not an image output; use a display output ({', '.join(viewer.DISPLAY_OUTPUTS)}) "
        f"or a linear colour ({', '.join(LINEAR_COLOURS)})"
    )


def write_image(path: Path, image: np.ndarray, kind: str) -> None:
    """``image`` (``H x W x 3``, ``[0, 1]``) as an 8-bit (``display``) or 16-bit linear PNG."""
    from seathru_nerfstudio.data.io import write_png16

    if kind == "linear":
        write_png16(path, image)
        return
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    codes = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)[..., ::-1]
    if not cv2.imwrite(str(path), np.ascontiguousarray(codes)):
        raise OSError(f"{path}: could not write image")


def relative_names(filenames: Sequence[Path]) -> List[Path]:
    """Each input's path below the inputs' common folder, with the suffix ``.png``."""
    root = Path(os.path.commonpath([str(Path(f).parent) for f in filenames]))
    return [Path(f).relative_to(root).with_suffix(".png") for f in filenames]


def split_datasets(pipeline, split: str) -> List[Tuple[str, object]]:
    """``(split, dataset)`` for ``train``, ``test`` or ``train+test``."""
    datamanager = pipeline.datamanager
    chosen = {"train": datamanager.train_dataset, "test": datamanager.eval_dataset}
    return [(name, chosen[name]) for name in split.split("+")]


@dataclass
class RestoreCommand:
    """Render every training and test photo of a run without the water, named as the inputs."""

    load_config: Path
    """The run's ``config.yml``."""
    output_dir: Path = Path("restored")
    """Where to write ``<output>/<input name>.png``."""
    outputs: List[str] = field(default_factory=lambda: ["clean_display", "clean"])
    """Display outputs (8-bit sRGB PNG) and linear colours (16-bit linear PNG) to write."""
    split: Literal["train", "test", "train+test"] = "train+test"
    """Which photos."""
    overwrite: bool = False
    """Replace a non-empty ``output-dir``."""

    def main(self) -> int:
        try:
            kinds = {name: image_kind(name) for name in self.outputs}
        except ValueError as error:
            print(f"seathru-restore: {error}", file=sys.stderr)
            return 2
        if not self.load_config.is_file():
            print(f"seathru-restore: {self.load_config}: no such file (give a run's config.yml)", file=sys.stderr)
            return 2
        from nerfstudio.utils.eval_utils import eval_setup

        from seathru_nerfstudio.data.io import OutputFolderError, atomic_output_folder

        _, pipeline, _, _ = eval_setup(self.load_config, test_mode="test")
        datasets = split_datasets(pipeline, self.split)
        names = relative_names([f for _, dataset in datasets for f in dataset.image_filenames])
        count = 0
        try:
            with atomic_output_folder(self.output_dir, self.overwrite) as build:
                for _, dataset in datasets:
                    cameras = dataset.cameras.to(pipeline.device)
                    for index in range(len(cameras)):
                        with torch.no_grad():
                            outputs = pipeline.model.get_outputs_for_camera(cameras[index : index + 1])
                        for name, kind in kinds.items():
                            write_image(build / name / names[count], outputs[name].cpu().numpy(), kind)
                        count += 1
        except OutputFolderError as error:
            print(f"seathru-restore: {error}", file=sys.stderr)
            return 1
        print(f"seathru-restore: {count} photos x {len(kinds)} outputs in {self.output_dir}")
        return 0


def entrypoint() -> None:
    """``seathru-restore``."""
    import tyro

    from seathru_nerfstudio.quiet import silence_upstream_warnings

    silence_upstream_warnings()
    raise SystemExit(tyro.cli(RestoreCommand).main())


if __name__ == "__main__":
    entrypoint()
