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


@pytest.mark.parametrize("vertical", [[0.0, 0.0, 2.0], [1.0, 0.0, 0.0], [0.6, -0.48, 0.64]])
def test_the_level_axes_complete_the_vertical_to_an_orthonormal_frame(vertical):
    """``(e1, e2, vertical)`` is right-handed and orthonormal, so a unit direction's ``sin(elevation)``
    and its two level components have squares summing to 1."""
    from seathru_nerfstudio.medium_field import level_axes, level_components

    v = torch.tensor(vertical)
    axes = level_axes(v)
    frame = torch.cat([axes, (v / v.norm())[:, None]], dim=1).double()
    torch.testing.assert_close(frame.T @ frame, torch.eye(3, dtype=torch.float64), atol=1e-6, rtol=0)
    assert float(torch.linalg.det(frame)) == pytest.approx(1.0, abs=1e-6)
    directions = torch.nn.functional.normalize(torch.randn(50, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    squares = level_components(directions, axes).square().sum(-1) + sin_elevation(directions, v / v.norm())[..., 0].square()
    torch.testing.assert_close(squares, torch.ones(50), atol=1e-5, rtol=0)


def test_the_veil_changes_round_the_horizon_within_the_range_held_and_scales_the_whole_path_radiance():
    """Vertical ``+z``: the level components are ``x`` (``e1``) and ``y`` (``z × x``). The factor is 1 at
    the held mean, linear in the components inside the held range, held at its value there outside
    it, never below 0; the veil is ``c_med`` times it. It is not in ``rendered_veil_gain`` (the
    backscatter density is not divided by it: the path radiance scales near and far alike)."""
    medium = SceneMedium(init_rgb=[0.1, 0.2, 0.4])
    medium.set_vertical([0.0, 0.0, 1.0])
    change = torch.tensor([[0.5, 0.2, -0.1], [0.0, 0.3, 0.0]])
    medium.set_veil_across(torch.tensor([0.1, 0.8]), change, torch.tensor([-0.5, 0.6]), torch.tensor([0.5, 1.0]))
    directions = torch.nn.functional.normalize(torch.tensor([
        [0.1, 0.8, 0.0], [0.3, 0.9, 0.1], [-0.9, 0.3, 0.0], [0.0, 0.0, -1.0], [0.9, -0.2, 0.1],
    ]), dim=-1)
    h = torch.stack([directions[:, 0].clamp(-0.5, 0.5), directions[:, 1].clamp(0.6, 1.0)], dim=1)
    expected = 1.0 + (h - torch.tensor([0.1, 0.8])) @ change
    torch.testing.assert_close(medium.across_gain(directions), expected.clamp_min(0.0), rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(medium(directions).rgb, torch.tensor([0.1, 0.2, 0.4]) * expected, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(medium.rendered_veil_gain(directions), torch.ones(5, 3))
    assert torch.equal(medium(directions).sigma_bs, SceneMedium(init_rgb=[0.1, 0.2, 0.4])(directions).sigma_bs)

    medium.set_veil_across(torch.zeros(2), torch.full((2, 3), -1e30), torch.full((2,), -1.0), torch.ones(2))
    for dtype in (torch.float16, torch.bfloat16):
        veil = medium(directions.to(dtype)).rgb
        assert bool(torch.isfinite(veil).all()) and bool((veil >= 0).all())
        assert bool(torch.isfinite(medium.rendered_veil_gain(directions.to(dtype))).all())


def test_a_checkpoint_from_before_the_change_round_the_horizon_loads_without_one_and_a_second_pass_keeps_it():
    """A checkpoint without the change round the horizon loads strictly into a new medium, whose factor
    is 1. nerfstudio's pipeline loads the model's keys, then its own (none of the model's) into every
    module with ``strict=False``: that second pass keeps the change the first one loaded."""
    older = SceneMedium(init_rgb=0.2)
    state = {k: v for k, v in older.state_dict().items() if not k.startswith("veil_across")}
    loaded = SceneMedium()
    loaded.load_state_dict(state)
    directions = torch.nn.functional.normalize(torch.randn(20, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    torch.testing.assert_close(loaded.across_gain(directions), torch.ones(20, 3))
    torch.testing.assert_close(loaded(directions).rgb, older(directions).rgb)

    trained = SceneMedium(init_rgb=0.2)
    trained.set_veil_across(torch.tensor([0.0, 0.9]), torch.full((2, 3), 0.3), -torch.ones(2), torch.ones(2))
    pipeline = torch.nn.ModuleDict({"model": SceneMedium()})
    pipeline["model"].load_state_dict(trained.state_dict(), strict=True)
    assert pipeline.load_state_dict({}, strict=False).missing_keys  # the second pass: none of the model's keys
    torch.testing.assert_close(pipeline["model"].across_gain(directions), trained.across_gain(directions))


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
