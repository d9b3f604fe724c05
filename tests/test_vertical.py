"""The scene's vertical from cameras held level (seathru_nerfstudio.vertical)."""

import math

import pytest
import torch

from seathru_nerfstudio.medium_field import SceneMedium, sin_elevation
from seathru_nerfstudio.vertical import MEAN_UP_WEIGHT, level_direction, scene_vertical


def _rotation_about(axis, angle):
    """Rodrigues' rotation matrix (float64) by ``angle`` radians about the unit ``axis``."""
    axis = torch.as_tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _cameras(yaws_deg, pitch_deg, rolls_deg=None, frame=None):
    """OpenGL camera-to-world (N, 3, 4) in a y-up world turned by ``frame``: each camera looks along
    -z turned by its yaw about +y, then pitched about its right vector, then rolled about its axis."""
    rolls_deg = rolls_deg if rolls_deg is not None else [0.0] * len(yaws_deg)
    frame = frame if frame is not None else torch.eye(3, dtype=torch.float64)
    poses = []
    for yaw, roll in zip(yaws_deg, rolls_deg):
        yawed = _rotation_about([0, 1, 0], math.radians(yaw))
        pitched = yawed @ _rotation_about([1, 0, 0], math.radians(pitch_deg))
        rolled = pitched @ _rotation_about([0, 0, 1], math.radians(roll))
        poses.append(torch.cat([frame @ rolled, torch.zeros(3, 1, dtype=torch.float64)], dim=1))
    return torch.stack(poses)


def _angle_deg(a, b):
    return math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b) / float(a.norm() * b.norm())))))


def test_pitched_level_cameras_give_the_true_vertical_where_the_mean_up_is_off_by_the_pitch():
    frame = _rotation_about([0.3, -0.2, 0.9], 1.1)  # any scene frame: the world's +y goes here
    truth = frame @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    cameras = _cameras([-40, -25, -10, 0, 15, 30, 45], pitch_deg=-35.0, frame=frame)
    vertical = scene_vertical(cameras)
    mean_up = cameras[:, :, 1].mean(dim=0)
    assert _angle_deg(mean_up, truth) > 30.0  # what nerfstudio's "up" orientation takes as +z
    assert _angle_deg(vertical, truth) < 0.5  # only the tie-break's pull (module docstring) remains
    assert float(vertical.norm()) == pytest.approx(1.0)


def test_the_tie_break_pulls_by_about_its_weight_over_the_yaw_spread():
    """With the right vectors' second eigenvalue ``λ``, the pull towards the mean up is about ``μ/λ`` of
    the angle between them (first-order perturbation of the eigenvector)."""
    truth = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    yaws = [-40, -25, -10, 0, 15, 30, 45]
    cameras = _cameras(yaws, pitch_deg=-35.0)
    rights = cameras[:, :, 0]
    second = float(torch.linalg.eigvalsh(rights.T @ rights / len(yaws))[1])
    mean_up = cameras[:, :, 1].mean(dim=0)
    expected = MEAN_UP_WEIGHT / second * _angle_deg(mean_up, truth)
    assert _angle_deg(scene_vertical(cameras), truth) == pytest.approx(expected, rel=0.2)


def test_cameras_facing_one_way_give_their_mean_up_without_roll():
    cameras = _cameras([10.0] * 5, pitch_deg=-20.0, rolls_deg=[0.0] * 5)
    mean_up = cameras[:, :, 1].mean(dim=0)
    assert torch.allclose(scene_vertical(cameras), mean_up / mean_up.norm(), atol=1e-9)


def test_small_rolls_move_the_vertical_by_less_than_the_rolls():
    generator = torch.Generator().manual_seed(0)
    yaws = torch.linspace(-30, 30, 24).tolist()
    rolls = (2.0 * torch.randn(24, generator=generator, dtype=torch.float64)).tolist()  # 2° spread
    cameras = _cameras(yaws, pitch_deg=-25.0, rolls_deg=rolls)
    truth = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    assert _angle_deg(scene_vertical(cameras), truth) < 2.0
    assert _angle_deg(cameras[:, :, 1].mean(dim=0), truth) > 20.0


def test_degenerate_inputs_give_plus_z():
    assert scene_vertical(torch.zeros(0, 3, 4)).tolist() == [0.0, 0.0, 1.0]
    up, down = _cameras([0.0], 0.0), _cameras([0.0], 0.0)
    down[:, :, 1] *= -1  # two cameras whose up vectors cancel
    assert scene_vertical(torch.cat([up, down])).tolist() == [0.0, 0.0, 1.0]


@pytest.mark.parametrize("vertical", [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.6, -0.48, 0.64]])
def test_level_direction_is_a_unit_vector_orthogonal_to_the_vertical(vertical):
    v = torch.tensor(vertical, dtype=torch.float64)
    level = level_direction(v)
    assert float(level.norm()) == pytest.approx(1.0) and float(level @ v) == pytest.approx(0.0, abs=1e-12)


def test_the_veil_rises_along_the_scene_vertical():
    medium = SceneMedium(init_rgb=0.2)
    tilt = math.radians(30.0)
    vertical = torch.tensor([0.0, math.sin(tilt), math.cos(tilt)])
    medium.set_vertical(vertical * 3.0)  # normalised on the way in
    medium.set_veil_rise(0.0, torch.tensor([1.0, 1.0, 1.0]), 1.0)
    level = torch.tensor([[0.0, -math.cos(tilt), math.sin(tilt)]])  # looks up by 30° in the scene's +z, level here
    straight_up = vertical[None]
    assert float(sin_elevation(level, medium.vertical)) == pytest.approx(0.0, abs=1e-6)
    assert torch.allclose(medium.veil_gain(level), torch.ones(1, 3), atol=1e-6)
    assert torch.allclose(medium.veil_gain(straight_up), torch.full((1, 3), 2.0), atol=1e-6)
    assert "vertical" not in medium.state_dict()  # from the data at every start


@pytest.mark.parametrize("vertical", [[0.0, 0.0, 0.0], [float("nan"), 0.0, 1.0], [float("inf"), 0.0, 0.0]])
def test_a_vertical_without_a_direction_is_refused(vertical):
    medium = SceneMedium()
    with pytest.raises(ValueError, match="finite non-zero"):
        medium.set_vertical(vertical)
    assert medium.vertical.tolist() == [0.0, 0.0, 1.0]  # left as it was


def test_a_checkpoint_with_one_start_of_the_rise_loads_it_for_every_channel():
    """Checkpoints from before the rise started per channel hold one ``veil_rise_from``: it loads into
    all three channels, and the veil is the one that checkpoint rendered."""
    older = SceneMedium(init_rgb=0.2)
    older.set_veil_rise(0.1, torch.tensor([1.0, 2.0, 3.0]), 0.5)
    state = older.state_dict()
    state["veil_rise_from"] = torch.tensor(0.1)
    loaded = SceneMedium()
    loaded.load_state_dict(state)
    assert loaded.veil_rise_from.tolist() == pytest.approx([0.1, 0.1, 0.1])
    up = torch.tensor([[0.0, 0.0, 1.0]])
    torch.testing.assert_close(loaded(up).rgb, older(up).rgb)
