"""``seathru-process-data``: RAW or 16-bit captures -> a linear SeaThru-NeRF dataset.

Usage::

    seathru-process-data --data <folder of RAW/16-bit files> --output-dir <dataset>

Steps: decode to linear camera RGB (rawpy), optional area downscale, one white balance for
the whole set (the paper's 0.5% per-channel clipping), 16-bit linear PNGs in
``<out>/images/``, then poses with pycolmap on display-transformed copies, written as
``<out>/sparse/0``, ``<out>/transforms.json`` (load with ``nerfstudio-data``) and
``<out>/poses_bounds.npy`` (load with ``seathru-data``). ``<out>/white_balance.json``
records the clip points and gains.

Everything is built in a hidden sibling folder and renamed into place at the end, so an
interrupted or failed run leaves no half-written dataset; the input folder is only read.
"""

from __future__ import annotations

import hashlib
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import tyro

from nerfstudio.utils.rich_utils import CONSOLE, get_progress
from seathru_nerfstudio.data.io import atomic_output_folder, check_output_folder, check_writable_parent, to_uint16, write_png16
from seathru_nerfstudio.data.raw import (
    LINEAR_EXTENSIONS,
    RAW_EXTENSIONS,
    ChannelHistogram,
    RawDecodeError,
    WhiteBalance,
    WhiteBalanceMethod,
    downscale_to_long_side,
    estimate_white_balance,
    image_sizes_summary,
    is_raw,
    read_input_image,
)
from seathru_nerfstudio.data.sfm import (
    MIN_REGISTERED_FRACTION,
    MatchingMethod,
    SfmResult,
    report,
    run_sfm,
)
from seathru_nerfstudio.data.sfm_images import write_display_copy
from seathru_nerfstudio.data.sfm_outputs import write_outputs
from seathru_nerfstudio.input_errors import InputError, exit_on_input_error
from seathru_nerfstudio.quiet import silence_upstream_warnings


class ProcessDataError(InputError):
    """The input cannot be turned into a dataset; the message says why and what to do."""


@dataclass
class ProcessSeathruData:
    """Turn a folder of RAW (NEF, DNG, CR2, ARW, RAF, ORF, RW2, ...) or 16-bit linear TIFF/PNG
    captures into a linear SeaThru-NeRF dataset with poses."""

    data: Path
    """Folder holding the captures (not searched recursively). Never modified."""
    output_dir: Path
    """Dataset folder to create: images/, sparse/0, transforms.json, poses_bounds.npy."""
    white_balance: WhiteBalanceMethod = "percentile"
    """percentile (the paper's): clip each channel at its clip-percent / 100-clip-percent points, map the upper one to 1. grey-world: same clipping, equal channel means. camera: the camera's as-shot multipliers (RAW only), same clipping. none: sensor values as decoded. One set of gains for all images."""
    clip_percent: float = 0.5
    """Per-channel clipping percentile for white balance (the paper uses 0.5)."""
    max_long_side: Optional[int] = None
    """Downscale (area average, linear-preserving) so the long side is at most this many px."""
    camera_model: Literal["OPENCV", "SIMPLE_RADIAL", "RADIAL", "PINHOLE", "SIMPLE_PINHOLE"] = "OPENCV"
    """COLMAP camera model shared by all images (OPENCV, as in the published SeaThru-NeRF data)."""
    focal_length_px: Optional[float] = None
    """The lens's focal length in pixels of the written images, where known (in water behind a flat port about 1.33 × the value in air): SfM starts there, not at 1.2 × the long side, and still refines it."""
    matching_method: MatchingMethod = "auto"
    """auto: exhaustive up to 50 images, sequential (video-like captures) beyond."""
    min_registered_fraction: float = MIN_REGISTERED_FRACTION
    """Fail (exit status 1, nothing written) when structure from motion registers less than this share of the images; 0 keeps any registration."""
    skip_sfm: bool = False
    """Only decode and white-balance; write no poses."""
    overwrite: bool = False
    """Replace an output folder that already holds files."""
    verbose: bool = False
    """Show COLMAP's own log."""

    def main(self) -> "ProcessReport":
        return process(self)


@dataclass
class ProcessReport:
    """What a run produced (file names are the output ``images/`` names)."""

    output_dir: Path
    images: list[str]
    skipped: dict[str, str] = field(default_factory=dict)
    """Input files that could not be read, with the reason."""
    white_balance: WhiteBalance = field(default_factory=WhiteBalance.identity)
    sfm: Optional[SfmResult] = None


def find_captures(data: Path) -> list[Path]:
    """The RAW or linear image files directly in ``data``, sorted by name."""
    if not data.is_dir():
        raise ProcessDataError(f"--data {data} is not a folder")
    files = sorted(p for p in data.iterdir() if p.is_file() and not p.name.startswith("."))
    raws = [p for p in files if is_raw(p)]
    linears = [p for p in files if p.suffix.lower() in LINEAR_EXTENSIONS]
    if not raws and not linears:
        raise ProcessDataError(
            f"{data} holds no RAW ({', '.join(sorted(RAW_EXTENSIONS))}) or 16-bit TIFF/PNG files"
        )
    if raws and linears:
        raise ProcessDataError(
            f"{data} mixes RAW files ({raws[0].name}, ...) with TIFF/PNG ({linears[0].name}, ...): their "
            "colour spaces differ; process them separately"
        )
    captures = raws or linears
    ignored = [p.name for p in files if p not in captures]
    if ignored:  # e.g. the JPEGs of a RAW+JPEG capture
        CONSOLE.print(f"Ignoring {len(ignored)} other file(s) in {data}: {', '.join(ignored[:5])}{' ...' * (len(ignored) > 5)}")
    stems: dict[str, Path] = {}
    for path in captures:
        if path.stem in stems:
            raise ProcessDataError(f"{path.name} and {stems[path.stem].name} would both become {path.stem}.png")
        stems[path.stem] = path
    return captures


def _check_output(output_dir: Path, data: Path, overwrite: bool) -> None:
    out, src = output_dir.resolve(), data.resolve()
    if out == src or out in src.parents:
        raise ProcessDataError(f"--output-dir {output_dir} would contain the input folder {data}; pick another folder")
    check_output_folder(output_dir, overwrite)
    check_writable_parent(output_dir)


def process(config: ProcessSeathruData) -> ProcessReport:
    """Run the whole pipeline; raises :class:`ProcessDataError`, ``SfmError`` or
    ``OutputFolderError`` with nothing written when it cannot produce a dataset."""
    if not 0.0 <= config.clip_percent < 50.0:
        raise ProcessDataError(f"--clip-percent must be in [0, 50), got {config.clip_percent}")
    if config.max_long_side is not None and config.max_long_side < 16:
        raise ProcessDataError(f"--max-long-side must be at least 16 px, got {config.max_long_side}")
    if not 0.0 <= config.min_registered_fraction <= 1.0:
        raise ProcessDataError(f"--min-registered-fraction must be in [0, 1], got {config.min_registered_fraction}")
    if config.focal_length_px is not None and not (math.isfinite(config.focal_length_px) and config.focal_length_px > 0):
        raise ProcessDataError(f"--focal-length-px must be a positive number of pixels, got {config.focal_length_px}")
    captures = find_captures(config.data)
    _check_output(config.output_dir, config.data, config.overwrite)
    if config.white_balance == "camera" and not is_raw(captures[0]):
        raise ProcessDataError("--white-balance camera needs RAW files (TIFF/PNG carry no as-shot multipliers)")
    with atomic_output_folder(config.output_dir, config.overwrite) as build:
        report_ = _build(config, captures, build)
        shutil.rmtree(build / "_work")
    CONSOLE.print(f"[bold green]Done: {len(report_.images)} linear 16-bit images in {config.output_dir / 'images'}")
    return report_


def _build(config: ProcessSeathruData, captures: list[Path], build: Path) -> ProcessReport:
    from seathru_nerfstudio.data.linear_images import ImageReadError

    work = build / "_work"
    decoded_dir, display_dir = work / "decoded", work / "display"
    decoded_dir.mkdir(parents=True)
    histogram = ChannelHistogram()
    sizes: dict[str, tuple[int, int]] = {}
    skipped: dict[str, str] = {}
    copies: dict[str, list[str]] = {}  # pixel hash -> files

    # Pass 1: decode, downscale, accumulate the joint histogram. The decoded frames wait in
    # the scratch folder as uint16 (exact for RAW, which LibRaw outputs at 16 bits).
    progress = get_progress("[bold yellow]Decoding to linear RGB", suffix="images/s")
    with progress:
        for path in progress.track(captures):
            try:
                image = read_input_image(path, use_camera_wb=config.white_balance == "camera")
            except (RawDecodeError, ImageReadError) as error:
                skipped[path.name] = str(error)
                progress.console.print(f"[bold yellow]Warning: skipping {path.name}: {error}")
                continue
            image = downscale_to_long_side(image, config.max_long_side)
            sizes[path.name] = image.shape[:2]
            histogram.add(image)
            codes = to_uint16(image)
            copies.setdefault(hashlib.sha1(codes.tobytes()).hexdigest(), []).append(path.name)
            np.save(decoded_dir / f"{path.stem}.npy", codes)
    if not sizes:
        raise ProcessDataError(f"none of the {len(captures)} files in {config.data} could be read: {skipped}")
    if len(set(sizes.values())) > 1:
        raise ProcessDataError(
            "the images do not all have the same size, but SeaThru-NeRF assumes one camera. Sizes: "
            + image_sizes_summary(sizes)
        )

    duplicates = [names for names in copies.values() if len(names) > 1]
    if duplicates and not config.skip_sfm:
        raise ProcessDataError(
            f"{config.data} holds identical images: {'; '.join(' = '.join(names) for names in duplicates)}. Structure "
            "from motion needs the camera to move between shots; remove the copies"
        )

    white_balance = estimate_white_balance(histogram, config.white_balance, config.clip_percent)
    CONSOLE.print(
        f"White balance ({white_balance.method}): gains R,G,B = {', '.join(f'{g:.3f}' for g in white_balance.gains)}"
    )

    # Pass 2: the same white balance for every view, 16-bit linear PNGs + SIFT copies.
    names = []
    progress = get_progress("[bold yellow]White balance + writing 16-bit PNGs", suffix="images/s")
    with progress:
        for source in progress.track([p for p in captures if p.name in sizes]):
            image = np.load(decoded_dir / f"{source.stem}.npy").astype(np.float32) / 65535.0
            image = white_balance.apply(image)
            name = f"{source.stem}.png"
            write_png16(build / "images" / name, image)
            if not config.skip_sfm:
                write_display_copy(display_dir / name, image)
            names.append(name)
    white_balance.save(build / "white_balance.json")
    result = None
    if not config.skip_sfm:
        result = run_sfm(
            display_dir,
            work / "sfm",
            camera_model=config.camera_model,
            matching=config.matching_method,
            verbose=config.verbose,
            min_registered_fraction=config.min_registered_fraction,
            source=config.data,
            focal_length_px=config.focal_length_px,
        )
        report(result)
        write_outputs(result, build)
    if skipped:
        CONSOLE.print(f"[bold yellow]Warning: {len(skipped)} unreadable file(s) left out: {', '.join(skipped)}")
    return ProcessReport(
        output_dir=config.output_dir, images=names, skipped=skipped, white_balance=white_balance, sfm=result
    )


def entrypoint() -> None:
    """Console script: exit status 1 with a one-line reason on bad input."""
    silence_upstream_warnings()
    config = tyro.cli(ProcessSeathruData)
    with exit_on_input_error():
        config.main()


if __name__ == "__main__":
    entrypoint()
