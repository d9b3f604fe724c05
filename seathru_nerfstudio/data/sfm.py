"""Camera poses with pycolmap (no COLMAP binary); :mod:`~seathru_nerfstudio.data.sfm_outputs` writes
the files nerfstudio / LLFF expect.

Conventions
-----------
* SIFT runs on an 8-bit copy of each linear image (:mod:`~seathru_nerfstudio.data.sfm_images`).
  The copies carry the same file names as the linear images, so COLMAP's image names are the
  dataset's image names.
* COLMAP world units are arbitrary up to the written files: the mapper's scale is rescaled
  (:func:`~seathru_nerfstudio.data.sfm_outputs.normalise_gauge`) so the 99th percentile of the
  points' z-depths is 32.77 units,
  which the uint16 depth PNGs hold without wrapping. Camera frames are OpenCV (x right, y down, z forward), ``cam_from_world`` maps world to camera.
* ``transforms.json`` is written by nerfstudio's own ``colmap_to_json`` (OpenGL camera
  axes, z-up world, like ``ns-process-data``). ``poses_bounds.npy`` follows LLFF's
  ``imgs2poses``: one row per registered image sorted by name, a 3×5 matrix
  ``[down, right, backwards, centre, (h, w, f)]`` flattened, then near and far, the 0.1% /
  99.9% depth percentiles of the sparse points the image sees, in COLMAP units.
"""

from __future__ import annotations

import contextlib
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Literal, Optional

import cv2  # before pycolmap, always: see the note below
import pycolmap

from nerfstudio.utils.rich_utils import CONSOLE, get_progress, status
from seathru_nerfstudio.data.sfm_models import complete_starts, model_rank, models_disagreement_deg, num_observations
from seathru_nerfstudio.input_errors import InputError

# Import order matters: pycolmap's extension exports its own zlib symbols. If it is loaded
# before OpenCV, OpenCV's libpng binds deflate* to it and cv2.imwrite(".png") aborts the
# process ("free(): invalid pointer"). Importing cv2 first binds OpenCV to the system zlib.

MatchingMethod = Literal["auto", "exhaustive", "sequential"]
EXHAUSTIVE_MAX_IMAGES = 50
"""``auto`` matching pairs every image with every other up to this many images (quadratic
cost), then switches to sequential matching (each image against its next neighbours)."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


class SfmError(InputError):
    """Structure from motion could not produce a usable reconstruction from these images."""


@dataclass
class SfmResult:
    """The largest reconstruction and which images it did / did not register."""

    reconstruction: pycolmap.Reconstruction
    registered: list[str]
    unregistered: list[str]
    attempts: list[int] = field(default_factory=list)
    """Images registered by the best model of each mapper attempt, in order (:data:`MAPPER_ATTEMPTS` for each
    camera start of each of the :data:`DESCRIPTOR_PASSES` that ran)."""
    observations: list[int] = field(default_factory=list)
    """Feature observations (:func:`~seathru_nerfstudio.data.sfm_models.num_observations`) of that model, per attempt."""
    descriptors: list[str] = field(default_factory=list)
    """The descriptors (:data:`DESCRIPTOR_PASSES`) each attempt mapped with."""
    cameras: list[str] = field(default_factory=list)
    """The camera start (:func:`camera_starts`) each attempt mapped from."""
    kept: int = 0
    """Index of the attempt whose model is ``reconstruction``."""
    disagreement_deg: list[float | None] = field(default_factory=list)
    """Per attempt, :func:`~seathru_nerfstudio.data.sfm_models.rotation_disagreement_deg` of its model against the kept one over the
    images both registered (degrees; ``None`` under 3 shared images)."""

    @property
    def registration_rate(self) -> float:
        return len(self.registered) / max(1, len(self.registered) + len(self.unregistered))


MIN_REGISTERED_FRACTION = 0.5
"""Default of ``--min-registered-fraction``: below this share of the images in the best model,
structure from motion fails (a NeRF of a few views of a larger capture is not what was asked)."""
RETRY_BELOW_FRACTION = 0.8
"""A start of the mapper that registers this share of the images is complete (:data:`COMPLETE_STARTS`);
while none is, the images are matched again (:data:`DESCRIPTOR_PASSES`)."""
COMPLETE_STARTS = 2
"""The mapper runs from other initial pairs (:data:`MAPPER_ATTEMPTS`) until this many of its
starts hold at least :data:`RETRY_BELOW_FRACTION` of the images, or its settings run out: a model
can hold every image and still be wrong, and two complete starts let the one that explains more
(:func:`~seathru_nerfstudio.data.sfm_models.model_rank`) win. Bundle adjustment drops
observations it cannot explain, so a wrong model explains fewer. On a path-traced fog scene
(``seathru-pathtrace --preset fog --seed 1``, one focal length) the first start registered 24/24
views 5.2 degrees off the true rotations with the scene's depth halved, and explained 3981
observations at 0.62 px; the second and third registered the same 24 views 0.6 degrees off and
explained 4200 and 4190 at 0.56 px. With pooled SIFT alone, coastal layout 0's second start held
24/24 views 38 degrees off, and its third 24/24 at 1.1 degrees with more observations."""
MAPPER_ATTEMPTS: tuple[dict[str, float], ...] = (
    {},  # COLMAP's defaults
    # other initial pairs: more of them tried, weaker ones accepted, and a different sampling seed
    {"seed": 1, "init_num_trials": 400, "init_min_num_inliers": 50, "init_min_tri_angle": 8.0, "abs_pose_min_num_inliers": 15},
    # what a hard underwater capture (little texture, short baselines) may still register with
    {
        "seed": 2,
        "init_num_trials": 800,
        "init_min_num_inliers": 25,
        "init_min_tri_angle": 4.0,
        "abs_pose_min_num_inliers": 10,
        "abs_pose_min_inlier_ratio": 0.15,
    },
)
"""Incremental mapper settings, tried in order while the best model is small (the features and
matches are kept): each is deterministic, so the whole sequence is."""
DESCRIPTOR_PASSES: tuple[tuple[str, dict[str, bool]], ...] = (
    ("SIFT", {}),
    ("pooled SIFT", {"domain_size_pooling": True}),
)
"""Descriptors to extract and match, in order, each followed by the mapper's tries; the next pass runs
only while the best model holds less than :data:`RETRY_BELOW_FRACTION` of the images. Pooled SIFT
(DSP-SIFT: the descriptor averaged over a range of patch sizes) is more distinctive where noise
and a veil leave little texture, and Lowe's ratio test then keeps more true matches. On the
path-traced scenes (one focal length, display copies as shipped; ``seathru-pathtrace --preset P
--seed L``): turbid water layout 2 goes from 6/24 views (29 verified pairs) to 24/24 (72 pairs, 1.65
degrees median rotation error), coastal layout 5 from 17/24 (0.95 degrees) to 23/24 (1.10 degrees).
It is not the first pass: alone, it registered coastal layout 0 24/24 but 38 degrees off at the
mapper's second start (SIFT: 23/24, 1.49 degrees); with guided matching its five times more points
moved coastal's medium fit (beta_D 9 to 19% off, one run; docs/history.md, 2026-11-28). A relaxed
ratio test (0.9 instead of 0.8), the other way to keep more matches, registered coastal layouts 5
and 6 fully but 19 and 7 degrees off."""
SEED = 0


@contextlib.contextmanager
def _colmap_logging(verbose: bool, quiet_level: int = 2) -> Iterator[None]:
    """Unless ``verbose``, show only COLMAP's log lines of ``quiet_level`` and above (glog's levels:
    0 info, 1 warning, 2 error, 3 fatal)."""
    previous = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = quiet_level
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


PRIOR_PARAMS = {
    "SIMPLE_PINHOLE": "{f},{cx},{cy}",
    "PINHOLE": "{f},{f},{cx},{cy}",
    "SIMPLE_RADIAL": "{f},{cx},{cy},0",
    "RADIAL": "{f},{cx},{cy},0,0",
    "OPENCV": "{f},{f},{cx},{cy},0,0,0,0",
}
"""COLMAP's parameter order per camera model, for a starting focal length ``f`` (pixels), the principal
point at the image centre and no distortion."""
GUESSED_FOCAL_PER_LONG_SIDE = 1.2
"""COLMAP's guess of the focal length per long side; without a known one, :func:`camera_starts` maps from it
uncalibrated (fundamental matrices) and marked as a prior (essential matrices; still refined). Neither is right
everywhere: on path-traced clear layout 6 the uncalibrated start ended 14° off, the marked one 0.09°; on clear
layout 0 the marked one mirrored the cameras (docs/data.md)."""
WIDE_FOCAL_PER_LONG_SIDE = 0.5
"""The third start (90° across the long side), marked: bundle adjustment refines a focal length only near its
start, and on path-traced fog layout 9 the others ended 22% long, 17.5° off, this one 7.8° off (docs/data.md)."""


def prior_camera_params(camera_model: str, focal_length_px: Optional[float], image: Path) -> str:
    """COLMAP's ``camera_params`` string for ``camera_model`` starting at ``focal_length_px`` (pixels of
    ``image``), or at :data:`GUESSED_FOCAL_PER_LONG_SIDE` times its long side without one; the principal
    point at its centre. An :class:`SfmError` for a focal length that is not a finite positive number of
    pixels, a camera model without a starting layout, or an image that cannot be read."""
    if focal_length_px is not None and not (math.isfinite(focal_length_px) and focal_length_px > 0):
        raise SfmError(f"--focal-length-px must be a positive number of pixels, got {focal_length_px}")
    if camera_model not in PRIOR_PARAMS:
        raise SfmError(f"camera model {camera_model} is not one of {', '.join(PRIOR_PARAMS)}")
    shape = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if shape is None:
        raise SfmError(f"{image}: could not read the image to place the principal point")
    height, width = shape.shape[:2]
    focal = GUESSED_FOCAL_PER_LONG_SIDE * max(width, height) if focal_length_px is None else float(focal_length_px)
    return PRIOR_PARAMS[camera_model].format(f=focal, cx=width / 2.0, cy=height / 2.0)


def camera_starts(camera_model: str, focal_length_px: Optional[float], image: Path) -> list[tuple[str, str]]:
    """The shared camera's starts, each ``(label, camera_params)`` (:func:`prior_camera_params`; ``""``:
    COLMAP's uncalibrated guess): the known focal length alone where one is given, else the uncalibrated
    guess and :data:`GUESSED_FOCAL_PER_LONG_SIDE` and :data:`WIDE_FOCAL_PER_LONG_SIDE` × the long side marked;
    the model that explains the most is kept (:func:`run_sfm`)."""
    params = prior_camera_params(camera_model, focal_length_px, image)
    focal = float(params.split(",")[0])
    if focal_length_px is not None:
        return [(f"camera from {focal:.0f} px", params)]
    wide_focal = focal * WIDE_FOCAL_PER_LONG_SIDE / GUESSED_FOCAL_PER_LONG_SIDE
    wide = prior_camera_params(camera_model, wide_focal, image)
    return [("uncalibrated camera", ""), (f"camera from {focal:.0f} px", params), (f"camera from {wide_focal:.0f} px", wide)]


def mapper_options(attempt: dict[str, float]) -> pycolmap.IncrementalPipelineOptions:
    """The incremental mapper's options for one of :data:`MAPPER_ATTEMPTS`, deterministic.

    Repeatability needs one thread in the mapper (``num_threads``, its own and the inner
    mapper's: bundle adjustment and pose RANSAC on several threads give different models run to
    run) and fixed seeds."""
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = 3  # keep small models: we report a partial registration, not nothing
    options.num_threads = 1
    options.mapper.num_threads = 1
    seed = int(attempt.get("seed", SEED))
    options.random_seed = options.mapper.random_seed = options.triangulation.random_seed = seed
    if "init_num_trials" in attempt:
        options.init_num_trials = int(attempt["init_num_trials"])
    for name in ("init_min_num_inliers", "abs_pose_min_num_inliers"):
        if name in attempt:
            setattr(options.mapper, name, int(attempt[name]))
    for name in ("init_min_tri_angle", "abs_pose_min_inlier_ratio"):
        if name in attempt:
            setattr(options.mapper, name, float(attempt[name]))
    return options


def run_sfm(
    image_dir: Path,
    work_dir: Path,
    camera_model: str = "OPENCV",
    matching: MatchingMethod = "auto",
    verbose: bool = False,
    min_registered_fraction: float = MIN_REGISTERED_FRACTION,
    source: Path | str | None = None,
    focal_length_px: Optional[float] = None,
) -> SfmResult:
    """SIFT extraction, matching and incremental mapping on every image in ``image_dir``.

    One camera (``camera_model``, COLMAP name) is shared by all images; its focal length
    starts at ``focal_length_px`` (pixels of these images) where it is given, else from both of
    :func:`camera_starts` (no EXIF in the display copies), and is refined by bundle adjustment.
    ``work_dir`` receives a database per descriptor pass and camera start (``database.db``,
    ``database_1.db``, ...) and the mapper's models. Features are extracted and matched once per pass; a
    further camera start copies them and runs only the two-view verification again (:func:`_verify_again`).

    The same images give the same result: features are extracted on one thread (COLMAP numbers
    the images in the order its threads finish them, and the mapper breaks ties by number), and
    matched on one thread (on two, under load, about one run in a hundred matched other
    features and gave other poses), the two-view RANSAC has a fixed seed, and the mapper runs on
    one thread with fixed seeds
    (:func:`mapper_options`). For each camera start, until :data:`COMPLETE_STARTS` of its mapper starts
    hold :data:`RETRY_BELOW_FRACTION` of the images, the mapper runs again with the next of
    :data:`MAPPER_ATTEMPTS` (other initial pairs). While no start holds that share, the images are
    matched again with the next of :data:`DESCRIPTOR_PASSES` (pooled SIFT) and mapped as before.
    Over all tries the model with the most images wins, and among those the one that explains the
    most observations (:func:`~seathru_nerfstudio.data.sfm_models.model_rank`; the first, on a tie).

    Returns that model; images outside it are ``unregistered``. Raises :class:`SfmError` when no
    model could be built, or when it holds less than ``min_registered_fraction`` of the images.
    Messages name ``source`` (the user's folder; default ``image_dir``).
    """
    source = image_dir if source is None else source
    names = sorted(p.name for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(names) < 2:
        raise SfmError(f"structure from motion needs at least 2 images, {source} has {len(names)}")
    if not 0.0 <= min_registered_fraction <= 1.0:
        raise SfmError(f"--min-registered-fraction must be in [0, 1], got {min_registered_fraction}")
    starts = camera_starts(camera_model, focal_length_px, image_dir / names[0])
    work_dir.mkdir(parents=True, exist_ok=True)
    if matching == "auto":
        matching = "exhaustive" if len(names) <= EXHAUSTIVE_MAX_IMAGES else "sequential"

    best, candidates, descriptors, cameras = None, [], [], []

    def num_complete(models: list) -> int:
        counts = [m.num_reg_images() if m is not None else 0 for m in models]
        return complete_starts(counts, len(names), RETRY_BELOW_FRACTION)

    with _colmap_logging(verbose):
        for number, (label, sift) in enumerate(DESCRIPTOR_PASSES):
            if num_complete(candidates) > 0:
                break
            if number > 0:
                CONSOLE.print(
                    f"[yellow]The best model holds {best.num_reg_images() if best else 0}/{len(names)} images; "
                    f"matching again with {label} descriptors"
                )
            for start, (camera_label, camera_params) in enumerate(starts):
                count = number * len(starts) + start
                database = work_dir / ("database.db" if count == 0 else f"database_{count}.db")
                if start == 0:
                    _extract_and_match(database, image_dir, names, camera_model, camera_params, matching, sift, label, verbose)
                    matched = database
                else:  # the same features and matches; only the two-view geometry depends on the camera
                    _verify_again(matched, database, camera_params, verbose)
                these: list = []  # this camera start's models
                for k, attempt in enumerate(MAPPER_ATTEMPTS):
                    if num_complete(these) >= COMPLETE_STARTS:
                        break
                    if k >= COMPLETE_STARTS:  # beyond the minimum of starts
                        CONSOLE.print(
                            f"[yellow]{num_complete(these)} of the mapper's {len(these)} starts ({camera_label}) hold "
                            f"{RETRY_BELOW_FRACTION:.0%} of the {len(names)} images; trying again with other initial pairs "
                            f"({k + 1}/{len(MAPPER_ATTEMPTS)})"
                        )
                    tries = len(candidates)
                    # a start that builds no model logs an error ("Failed to create any sparse model"); report() and
                    # SfmError say what each start did, in words that name the user's folder
                    with _colmap_logging(verbose, quiet_level=3):
                        models = _map(database, image_dir, work_dir / f"models_{tries}", attempt, len(names), tries)
                    these.append(max(models.values(), key=model_rank, default=None))
                    candidates.append(these[-1])
                    descriptors.append(label)
                    cameras.append(camera_label)
                    if these[-1] is not None and (best is None or model_rank(these[-1]) > model_rank(best)):
                        best = these[-1]
    if best is None:
        raise SfmError(
            f"structure from motion registered none of the {len(names)} images of {source} "
            f"({len(candidates)} tries): no two views overlap with parallax. The camera must move between "
            "views (not only turn) and the views must share textured content; check for blur or texture-less water"
        )
    registered = sorted(best.images[i].name for i in best.reg_image_ids())
    unregistered = sorted(set(names) - set(registered))
    attempts = [m.num_reg_images() if m is not None else 0 for m in candidates]
    result = SfmResult(
        reconstruction=best,
        registered=registered,
        unregistered=unregistered,
        attempts=attempts,
        descriptors=descriptors,
        cameras=cameras,
        observations=[num_observations(m) if m is not None else 0 for m in candidates],
        kept=next(i for i, m in enumerate(candidates) if m is best),
        disagreement_deg=[None if m is None else models_disagreement_deg(best, m) for m in candidates],
    )
    if result.registration_rate < min_registered_fraction:
        raise SfmError(
            f"structure from motion registered only {len(registered)} of the {len(names)} images of {source} "
            f"({100 * result.registration_rate:.0f}%, best of {len(attempts)} tries), below --min-registered-fraction "
            f"{min_registered_fraction:g}. Not registered: {_shorten(unregistered)}. Add views that overlap them, "
            "or lower --min-registered-fraction to train on the registered part"
        )
    return result


def _verification_options() -> pycolmap.TwoViewGeometryOptions:
    """COLMAP's two-view verification options with a fixed RANSAC seed (default -1: a new seed, other inliers, every run)."""
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = SEED
    return verification


def _extract_and_match(
    database: Path,
    image_dir: Path,
    names: list[str],
    camera_model: str,
    camera_params: str,
    matching: str,
    sift: dict[str, bool],
    label: str,
    verbose: bool,
) -> None:
    """SIFT extraction (COLMAP's options, then ``sift``'s) and matching into ``database``, on one thread
    each, with fixed seeds (see :func:`run_sfm`); ``camera_params``: the camera's starting parameters
    (:func:`prior_camera_params`), which COLMAP marks as a prior focal length."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    reader.camera_params = camera_params
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = 3200
    extraction.num_threads = 1  # image numbers in name order (see run_sfm)
    for name, value in sift.items():
        setattr(extraction.sift, name, value)
    matching_options = pycolmap.FeatureMatchingOptions()
    matching_options.num_threads = 1  # other matches now and then on several threads (see run_sfm)
    verification = _verification_options()
    pycolmap.set_random_seed(SEED)
    with status(f"[bold yellow]Extracting {label} features from {len(names)} images...", verbose=verbose):
        pycolmap.extract_features(
            database,
            image_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
    with status(f"[bold yellow]Matching features ({matching})...", verbose=verbose):
        match = pycolmap.match_exhaustive if matching == "exhaustive" else pycolmap.match_sequential
        match(database, matching_options=matching_options, verification_options=verification, device=pycolmap.Device.cpu)


def _verify_again(matched: Path, database: Path, camera_params: str, verbose: bool) -> None:
    """Copy ``matched`` (features and matches of :func:`_extract_and_match`) to ``database``, give its camera
    ``camera_params`` marked as a prior, and run the two-view verification again with the same seeded options.
    ``database`` then holds what :func:`_extract_and_match` would write from these parameters, to the bit (the
    same keypoints, matches and inliers; extraction and descriptor matching do not read the camera), at the
    cost of the verification alone."""
    database.unlink(missing_ok=True)
    shutil.copyfile(matched, database)
    db = pycolmap.Database.open(str(database))
    try:
        (camera,) = db.read_all_cameras()
        camera.params = [float(value) for value in camera_params.split(",")]
        camera.has_prior_focal_length = True
        db.update_camera(camera)
        db.clear_two_view_geometries()
    finally:
        db.close()
    verifier = pycolmap.GeometricVerifierOptions()
    verifier.num_threads = 1  # as the matcher's (see run_sfm)
    pycolmap.set_random_seed(SEED)
    with status("[bold yellow]Verifying the matches under the marked camera...", verbose=verbose):
        pycolmap.geometric_verification(database, verifier_options=verifier, two_view_geometry_options=_verification_options())


def _map(database: Path, image_dir: Path, output: Path, attempt: dict[str, float], total: int, number: int) -> dict:
    """One run of pycolmap's incremental mapper (:func:`mapper_options` of ``attempt``) with a progress bar."""
    output.mkdir(parents=True, exist_ok=True)
    progress = get_progress(f"[bold yellow]Incremental mapping, try {number + 1} (images registered)")
    with progress:
        task = progress.add_task("mapping", total=total)
        models = pycolmap.incremental_mapping(
            database, image_dir, output, options=mapper_options(attempt), next_image_callback=lambda: progress.advance(task)
        )
        progress.update(task, completed=max((m.num_reg_images() for m in models.values()), default=0))
    return models


def _shorten(names: list[str], limit: int = 8) -> str:
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def report(result: SfmResult) -> None:
    """Print how many images registered and name every one that did not."""
    total = len(result.registered) + len(result.unregistered)
    colour = "green" if not result.unregistered else ("yellow" if result.registration_rate >= 0.8 else "red")
    CONSOLE.print(
        f"[bold {colour}]Registered {len(result.registered)}/{total} images ({100 * result.registration_rate:.0f}%)"
    )
    label = [""] * len(result.attempts)
    for names in (result.descriptors, result.cameras):  # each named only where the tries differ in it
        if len(set(names)) > 1:
            label = [f"{before}, {name}" for before, name in zip(label, names)]
    others = [
        f"try {i + 1}{label[i]}: {n} images, {o} observations" + ("" if d is None else f", cameras {d:.1f}° apart (median)")
        for i, (n, o, d) in enumerate(zip(result.attempts, result.observations, result.disagreement_deg))
        if i != result.kept
    ]
    if others:
        CONSOLE.print(
            f"Kept the mapper's try {result.kept + 1}{label[result.kept]} ({len(result.registered)} images, "
            f"{result.observations[result.kept]} observations); {'; '.join(others)}"
        )
    if result.unregistered:
        CONSOLE.print(
            f"[bold yellow]Warning: {len(result.unregistered)} image(s) did not register and are left out of "
            f"transforms.json and sparse/0: {', '.join(result.unregistered)}"
        )
