"""Which of the mapper's models is kept, and how far two models orient their cameras apart
(``data/sfm_models.py``): closed forms on rotations, and the ranking on counted tracks."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from seathru_nerfstudio.data.sfm_models import complete_starts, model_rank, num_observations, rotation_angle_deg, rotation_disagreement_deg


def _cameras(n: int, seed: int) -> np.ndarray:
    return Rotation.random(n, random_state=seed).as_matrix()


@pytest.mark.parametrize("theta_deg", [0.0, 1e-6, 0.5, 90.0, 179.0])
def test_a_rotations_angle_is_its_axis_angle_to_the_last_digits(theta_deg: float) -> None:
    """About any axis, the angle comes back to a relative 1e-9, also at 1e-6 degrees, where an
    arccos of the trace would return 0 or lose most digits; the pose error of the path-traced
    scenes' alignment (``pathtrace.align.rotation_error_deg``) is the same angle."""
    from seathru_nerfstudio.data.pathtrace.align import rotation_error_deg

    axis = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    turn = Rotation.from_rotvec(np.radians(theta_deg) * axis).as_matrix()
    assert float(rotation_angle_deg(turn)) == pytest.approx(theta_deg, rel=1e-9, abs=1e-12)
    pose = np.eye(4)
    pose[:3, :3] = _cameras(1, 5)[0]
    turned = pose.copy()
    turned[:3, :3] = pose[:3, :3] @ turn
    assert rotation_error_deg(pose, turned) == pytest.approx(theta_deg, rel=1e-9, abs=1e-9)


def test_a_change_of_gauge_is_no_disagreement() -> None:
    """The same cameras seen in another world frame (every camera turned by one G) agree: 0 degrees
    (to rounding)."""
    cameras = _cameras(12, 0)
    gauge = Rotation.random(random_state=1).as_matrix()
    assert rotation_disagreement_deg(cameras, cameras @ gauge) < 1e-6
    assert rotation_disagreement_deg(cameras, cameras) < 1e-9


@pytest.mark.parametrize("theta_deg", [1e-5, 0.3, 5.0, 60.0, 170.0])
def test_two_halves_turned_apart_disagree_by_half_the_angle_each(theta_deg: float) -> None:
    """Half the cameras turned by theta about one axis against the other half (and the whole
    model in another gauge): the nearest common gauge lies half-way, so every camera, and the
    median, is theta / 2 off. Holds to the last digits for theta near 0, where an arccos of
    the trace would lose them."""
    cameras = _cameras(10, 2)
    gauge = Rotation.random(random_state=3).as_matrix()
    turn = Rotation.from_rotvec(np.radians(theta_deg) * np.array([0.6, 0.0, 0.8])).as_matrix()
    other = cameras @ gauge
    other[5:] = cameras[5:] @ turn @ gauge
    assert rotation_disagreement_deg(cameras, other) == pytest.approx(theta_deg / 2, rel=1e-6)
    assert rotation_disagreement_deg(other, cameras) == pytest.approx(theta_deg / 2, rel=1e-6)


def test_one_camera_off_does_not_move_the_median() -> None:
    """The median is robust: one of nine cameras turned by 30 degrees leaves it near 0 (the
    gauge moves by a ninth of the turn at most, so the others are under 30/9 degrees off)."""
    cameras = _cameras(9, 4)
    other = cameras.copy()
    other[0] = cameras[0] @ Rotation.from_rotvec([0.0, np.radians(30.0), 0.0]).as_matrix()
    assert 0.0 < rotation_disagreement_deg(cameras, other) < 30.0 / 9


def _model(num_images: int, track_lengths: list[int]) -> SimpleNamespace:
    """What model_rank reads of a pycolmap Reconstruction."""
    points = {k: SimpleNamespace(track=SimpleNamespace(length=lambda n=n: n)) for k, n in enumerate(track_lengths)}
    return SimpleNamespace(points3D=points, num_reg_images=lambda: num_images)


@pytest.mark.parametrize(("counts", "complete"), [([], 0), ([2, 21], 1), ([2, 21, 21], 2), ([20, 19, 24], 2), ([19, 19], 0)])
def test_a_start_is_complete_from_80_percent_of_the_images(counts: list[int], complete: int) -> None:
    """24 images at 80%: 19.2 is the line, so 19 registered views fall short and 20 count."""
    assert complete_starts(counts, 24, 0.8) == complete


def test_models_rank_by_images_then_by_observations() -> None:
    """More registered images wins whatever the tracks; with the same images, the model that
    keeps more observations (the summed track lengths) wins, however they are spread over points."""
    assert num_observations(_model(4, [2, 3, 5])) == 10
    assert num_observations(_model(4, [])) == 0
    fewer_images = _model(23, [9] * 1000)
    flattened = _model(24, [5] * 796)  # 3980 observations on more points
    right = _model(24, [6] * 700)  # 4200 on fewer
    ranked = sorted([fewer_images, flattened, right], key=model_rank)
    assert ranked == [fewer_images, flattened, right]


def test_the_report_names_the_try_kept_and_how_far_the_others_turn(capsys) -> None:
    """One line says which of the mapper's starts was kept and, for each other start, its images,
    observations and camera disagreement (none under 3 shared images)."""
    from seathru_nerfstudio.data.sfm import SfmResult, report

    names = [f"frame_{i:05d}.png" for i in range(24)]
    result = SfmResult(
        reconstruction=None,
        registered=names,
        unregistered=[],
        attempts=[24, 24, 2],
        observations=[3981, 4200, 12],
        kept=1,
        disagreement_deg=[2.37, 0.0, None],
    )
    report(result)
    out = " ".join(capsys.readouterr().out.split())
    assert "Kept the mapper's try 2 (24 images, 4200 observations)" in out
    assert "try 1: 24 images, 3981 observations, cameras 2.4° apart (median)" in out
    assert "try 3: 2 images, 12 observations" in out and "try 3: 2 images, 12 observations, cameras" not in out
    assert "SIFT" not in out  # one kind of descriptor: not named

    result.attempts, result.observations, result.disagreement_deg = [6, 3, 6, 18, 24], [138, 77, 138, 1136, 1310], [None] * 5
    result.descriptors, result.kept = ["SIFT"] * 3 + ["pooled SIFT"] * 2, 4
    report(result)
    out = " ".join(capsys.readouterr().out.split())
    assert "Kept the mapper's try 5, pooled SIFT (24 images, 1310 observations)" in out
    assert "try 1, SIFT: 6 images, 138 observations" in out and "try 4, pooled SIFT: 18 images" in out

    result.cameras = ["uncalibrated camera"] * 2 + ["camera from 288 px"] * 3
    report(result)
    out = " ".join(capsys.readouterr().out.split())
    assert "Kept the mapper's try 5, pooled SIFT, camera from 288 px (24 images, 1310 observations)" in out
    assert "try 1, SIFT, uncalibrated camera: 6 images" in out
