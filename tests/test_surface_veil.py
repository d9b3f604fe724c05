"""The veil in front of the surfaces: the histogram reader, its move with the fitted densities, and its window."""

from __future__ import annotations

import math

import pytest
import torch

from seathru_nerfstudio.medium_field import SceneMedium
from seathru_nerfstudio.model_config import SeathruModelConfig
from seathru_nerfstudio.phases import TrainingPhases
from seathru_nerfstudio.surface_veil import (
    LOG_RANGE_SPAN,
    MIN_SURFACE_SHARE,
    RANGE_BINS,
    RATIO_BINS,
    RATIO_TOP,
    SurfaceVeil,
    deep_bins,
)

VEIL = torch.tensor([0.05, 0.22, 0.44])
ATTENUATION = torch.tensor([0.3, 0.17, 0.12])  # per scene unit


def surface_rays(share: torch.Tensor, ranges: torch.Tensor, seed: int = 0, surface_light: float = 0.3):
    """Rays ending on surfaces at ``ranges`` (scene units) in the formation model with the veil ``share · VEIL``,
    ``β_B = β_D = ATTENUATION``, and a random surface colour up to ``surface_light``."""
    gen = torch.Generator().manual_seed(seed)
    J = torch.rand(ranges.shape[0], 3, generator=gen) * surface_light
    z = ranges[:, None]
    colour = J * torch.exp(-ATTENUATION * z) + share * VEIL * -torch.expm1(-ATTENUATION * z)
    return colour, VEIL.expand_as(colour), ranges[:, None], torch.ones(ranges.shape[0], 1)


def test_ratio_is_the_median_colour_over_veil_of_the_deep_surfaces():
    """Deep surfaces (optical depth >= 3) show ``r B∞`` plus at most 5% of their own light: the median
    ratio is within the own light's share and a bin of ``r``; shallow ones are not read."""
    share = torch.tensor([0.8, 0.9, 1.3])
    reader = SurfaceVeil()
    ranges = torch.exp(torch.linspace(math.log(0.5), math.log(60.0), 20000))
    reader.add(*surface_rays(share, ranges))
    ratio = reader.ratio(ATTENUATION, 3.0)
    for c in range(2):
        deep = ranges * ATTENUATION[c] >= 3.0
        own_light = 0.3 * math.exp(-3.0) / float(VEIL[c])  # the most a surface's own light can add, over the veil
        assert float(deep.float().mean()) > MIN_SURFACE_SHARE
        assert float(share[c]) - RATIO_TOP / RATIO_BINS <= float(ratio[c]) <= min(1.0, float(share[c]) + own_light + RATIO_TOP / RATIO_BINS)
    assert float(ratio[2]) == 1.0  # surfaces brighter than the open water: capped at one veil
    shallow = reader.ratio(ATTENUATION, 1e-3)  # every surface read: their own light lifts the median
    assert float(shallow[0]) > float(ratio[0]) + 0.05


def test_too_few_deep_surfaces_keep_one_veil_and_open_or_bad_rays_are_not_counted():
    reader = SurfaceVeil()
    shallow = 20_000
    deep = int(MIN_SURFACE_SHARE * shallow / 2)  # half the floor's share
    ranges = torch.cat([torch.full((shallow,), 1.0), torch.full((deep,), 40.0)])
    colour, veil, z, acc = surface_rays(torch.tensor([0.5, 0.5, 0.5]), ranges)
    reader.add(colour, veil, z, acc)
    torch.testing.assert_close(reader.ratio(ATTENUATION, 3.0), torch.ones(3, dtype=torch.float64))
    enough = SurfaceVeil()  # twice the floor's share is read: 40 units is 4.8 or more attenuation lengths
    enough.add(*surface_rays(torch.tensor([0.5, 0.5, 0.5]), torch.cat([ranges[:shallow], torch.full((4 * deep,), 40.0)])))
    own_light = 0.3 * math.exp(-float(ATTENUATION.min()) * 40.0) / float(VEIL.min())
    assert ((enough.ratio(ATTENUATION, 3.0) - 0.5).abs() <= own_light + RATIO_TOP / RATIO_BINS).all()
    before = reader.counts.clone()
    bad = torch.tensor([[float("nan"), 0.1, 0.1], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1]])
    reader.add(bad, VEIL.expand(4, 3), torch.tensor([[40.0], [40.0], [0.0], [40.0]]), torch.tensor([[1.0], [0.5], [1.0], [1.0]]))
    assert float((reader.counts - before).sum()) == 3.0  # only the last ray: NaN, open and zero-range rays are skipped
    assert SurfaceVeil().surface_rays == 0
    torch.testing.assert_close(SurfaceVeil().ratio(ATTENUATION, 3.0), torch.ones(3, dtype=torch.float64))


def test_counts_round_trip_through_a_state_dict_and_pool_without_distribution():
    reader = SurfaceVeil()
    reader.add(*surface_rays(torch.tensor([0.7, 0.8, 0.9]), torch.linspace(1.0, 50.0, 500)))
    again = SurfaceVeil()
    again.load_state_dict(reader.state_dict())
    assert torch.equal(again.counts, reader.counts)
    assert reader.pooled() is reader
    older = SurfaceVeil()
    older.load_state_dict({})  # a checkpoint from before the reader: nothing missing, nothing counted
    assert older.surface_rays == 0


def test_the_surface_veil_moves_in_log_space_with_the_fitted_densities_and_loads_from_older_checkpoints():
    medium = SceneMedium(init_density=0.5)
    torch.testing.assert_close(medium.surface_veil, torch.ones(3))
    target = torch.tensor([0.64, 0.81, 1.0])
    medium.start_move_to_fit(torch.full((6,), 0.25), target)
    held = torch.ones(6, dtype=torch.bool)
    medium.move_to_fit(0.5, held)
    torch.testing.assert_close(medium.surface_veil, target.sqrt())
    medium.move_to_fit(1.0, held)
    torch.testing.assert_close(medium.surface_veil, target)
    state = {k: v for k, v in medium.state_dict().items() if not k.startswith("surface_veil")}
    fresh = SceneMedium(init_density=0.5)
    result = fresh.load_state_dict(state, strict=True)
    assert not result.missing_keys
    torch.testing.assert_close(fresh.surface_veil, torch.ones(3))
    medium.start_move_to_fit(torch.full((6,), 0.25))  # no new veil: it stays where it is
    medium.move_to_fit(1.0, held)
    torch.testing.assert_close(medium.surface_veil, target)


@pytest.mark.parametrize("optical_depth", [3.0, None])
def test_surface_rays_are_read_in_the_second_half_before_the_fit(optical_depth):
    config = SeathruModelConfig(medium_first_steps=200, medium_fit_step=500)
    config.research.surface_veil_optical_depth = optical_depth
    reading = [step for step in range(0, 800) if TrainingPhases(config, step).reads_surface_veil]
    assert reading == ([] if optical_depth is None else list(range(350, 500)))
    assert not TrainingPhases(config, None).reads_surface_veil


def test_a_channel_is_read_only_where_its_deep_range_lies_within_the_far_bound():
    """A channel whose depth of 3 attenuation lengths lies past the SfM far bound (where the object field walls
    open water and far surfaces alike) is not read; one whose depth lies within it reads every deep ray, those
    past the bound included."""
    reader = SurfaceVeil()
    near = torch.exp(torch.linspace(math.log(0.5), math.log(18.0), 20000))  # within a far bound of 20
    wall = torch.full((500,), 40.0)  # past it: deep in every channel, showing 0.6 of the veil
    reader.add(*surface_rays(torch.tensor([0.8, 0.8, 0.8]), near))
    reader.add((VEIL * 0.6).expand(500, 3), VEIL.expand(500, 3), wall[:, None], torch.ones(500, 1))
    unbounded = reader.ratio(ATTENUATION, 3.0)
    bounded = reader.ratio(ATTENUATION, 3.0, max_range=20.0)
    assert float(unbounded[2]) < 0.62  # blue is deep (from 3 / 0.12 = 25 units) only on the wall
    assert float(bounded[2]) == 1.0 and float(reader.deep_share(ATTENUATION, 3.0, max_range=20.0)[2]) == 0.0
    torch.testing.assert_close(bounded[:2], unbounded[:2])  # red (10 units) and green (17.6) lie within it
    assert float(reader.deep_share(ATTENUATION, 3.0, max_range=20.0)[0]) > float((near * 0.3 >= 3.0).float().mean()) * 0.9
    assert bool(deep_bins(0.3, 3.0, 20.0)[-1]) and not bool(deep_bins(0.12, 3.0, 20.0).any())


def test_the_model_takes_its_sfm_far_bound_to_scene_units():
    """``read_surface_veil`` takes the model's far bound (world units, ``far_plane`` / scale) to scene units, as the
    rays' ranges are: with a scale of 2 and a far plane of 20 scene units, an attenuation of 0.25 per world unit
    (3 attenuation lengths at 24 scene units) lies past it and 1 per world unit (6 units) within it."""
    from seathru_nerfstudio.data.nerfstudio_data import SCALE_KEY
    from seathru_nerfstudio.surface_veil import read_surface_veil

    from tiny_training import tiny_model

    ranges = {"within": torch.full((500,), 15.0), "past": torch.full((2000,), 30.0)}
    shares = {"within": 0.8, "past": 0.6}
    for bounded in (True, False):
        metadata = {SCALE_KEY: 2.0, **({"far_plane": 20.0} if bounded else {})}
        model = tiny_model(metadata=metadata)
        assert (model.far_range == 10.0) if bounded else model.far_range is None
        for name, z in ranges.items():
            colour = (VEIL * shares[name]).expand(z.shape[0], 3)
            model.surface_veil_reader.add(colour, VEIL.expand(z.shape[0], 3), z[:, None], torch.ones(z.shape[0], 1))
        within = read_surface_veil(model, torch.full((3,), 1.0), step=499)  # the median: the 2000 rays at 30
        torch.testing.assert_close(within, torch.full((3,), shares["past"] + 0.005, dtype=torch.float64), atol=0.006, rtol=0)
        past = read_surface_veil(model, torch.full((3,), 0.25), step=499)  # only the rays at 30 units are deep
        if bounded:
            assert past is None  # one veil in every channel
        else:
            torch.testing.assert_close(past, within)
