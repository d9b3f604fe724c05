"""The SfM range spread: exact on a constructed pair of views, and what the dataparser reports."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from seathru_nerfstudio.data.range_diversity import range_spread

SIZE = 10
F = 10.0
C = 4.5  # pixel (4, 4)'s centre (+0.5) lies on the optical axis


def _camera_at(z: float, x: float = 0.0) -> np.ndarray:
    """Camera-to-world at (x, 0, z), looking along world -z."""
    c2w = np.zeros((3, 4))
    c2w[:, :3] = np.eye(3)
    c2w[0, 3], c2w[2, 3] = x, z
    return c2w


def _spread(depths, c2ws):
    n = len(depths)
    return range_spread(depths, np.stack(c2ws), np.full(n, F), np.full(n, F), np.full(n, C), np.full(n, C))


def test_a_point_two_views_apart_along_the_axis():
    """A point on the axis at z = -2, cameras at z = 0 and z = 1: ranges 2 and 3, so mean 2.5 and
    (population) std 0.5; a third view 5 to the side, whose image the point is outside of, adds nothing."""
    depth = np.zeros((SIZE, SIZE))
    depth[4, 4] = 2.0
    empty = np.zeros((SIZE, SIZE))
    spread = _spread([depth, empty, empty], [_camera_at(0.0), _camera_at(1.0), _camera_at(0.0, x=5.0)])
    assert spread.num_points == 1
    assert spread.mean_views == pytest.approx(2.0)
    assert spread.mean_range == pytest.approx(2.5)
    assert spread.spread == pytest.approx(0.5)
    assert spread.relative_spread == pytest.approx(0.2)


def test_cameras_in_one_plane_see_almost_no_spread_and_behind_counts_nothing():
    """Sideways motion of 0.1 at range 2 changes the range by ~0.0025 (second order), and a camera
    in front of the point does not see it at all."""
    depth = np.zeros((SIZE, SIZE))
    depth[4, 4] = 2.0
    side = _camera_at(0.0)
    side[0, 3] = 0.1
    spread = _spread([depth, np.zeros((SIZE, SIZE))], [_camera_at(0.0), side])
    expected_ranges = np.array([2.0, np.hypot(2.0, 0.1)])
    assert spread.spread == pytest.approx(expected_ranges.std())
    assert spread.relative_spread < 0.001
    alone = _spread([depth, np.zeros((SIZE, SIZE))], [_camera_at(0.0), _camera_at(-3.0)])
    assert alone.num_points == 0 and alone.spread == 0.0


def test_subsampling_keeps_the_statistics_of_a_uniform_layer():
    """Points all at range 2 from view 0 and seen from 1 further back: any evenly strided subset has
    the same per-point statistics, and no more points than asked for."""
    depth = np.zeros((SIZE, SIZE))
    depth[2:8, 2:8] = 2.0
    views = [depth, np.zeros((SIZE, SIZE))]
    cameras = [_camera_at(0.0), _camera_at(0.5)]
    every = _spread(views, cameras)
    few = range_spread(views, np.stack(cameras), *(np.full(2, value) for value in (F, F, C, C)), max_points_per_view=7)
    assert every.num_points == 36 and few.num_points <= 7
    assert few.mean_range == pytest.approx(every.mean_range, rel=0.02)
    assert few.spread == pytest.approx(every.spread, rel=0.05)


def test_dataparser_reports_it_in_world_units_and_a_deeper_rig_spreads_more(tmp_path: Path):
    """On seathru-synth scenes: the figure does not depend on nerfstudio's scene scaling, and
    ``--rig-depth`` raises it several times."""
    from seathru_nerfstudio.data.nerfstudio_data import RANGE_SPREAD_KEY, SeathruNerfstudioDataParserConfig
    from seathru_nerfstudio.data.synthetic import SynthConfig, generate

    def spread_of(scene: Path, **parser_options):
        parser = SeathruNerfstudioDataParserConfig(data=scene, **parser_options).setup()
        return parser.get_dataparser_outputs("train").metadata[RANGE_SPREAD_KEY]

    small = dict(width=40, height=30, num_views=10, supersample=1, sfm_points_per_view=60)
    flat = generate(SynthConfig(output_dir=tmp_path / "flat", **small))
    deep = generate(SynthConfig(output_dir=tmp_path / "deep", rig_depth=1.0, **small))
    flat_spread = spread_of(flat)
    assert flat_spread.num_points > 100 and 1.0 < flat_spread.mean_range < 2.6
    rescaled = spread_of(flat, scale_factor=3.0, auto_scale_poses=False)
    assert rescaled.spread == pytest.approx(flat_spread.spread, rel=1e-6)
    assert rescaled.mean_range == pytest.approx(flat_spread.mean_range, rel=1e-6)
    assert spread_of(deep).spread > 3 * flat_spread.spread


def test_a_non_positive_point_budget_is_refused():
    depth = np.zeros((SIZE, SIZE))
    depth[4, 4] = 2.0
    for budget in (0, -3):
        with pytest.raises(ValueError, match="max_points_per_view"):
            range_spread([depth], np.stack([_camera_at(0.0)]), np.full(1, F), np.full(1, F), np.full(1, C), np.full(1, C),
                         max_points_per_view=budget)  # fmt: skip
