"""The scene contraction that starts at the scene (``ContractionBeyond``) and the frustum
extent that sizes it."""

from __future__ import annotations

import math

import pytest
import torch

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.utils.math import Gaussians
from seathru_nerfstudio.contraction import ContractionBeyond
from seathru_nerfstudio.data.nerfstudio_data import EXTENT_KEY, frustum_extent


def test_radius_one_is_nerfstudios_contraction() -> None:
    x = torch.randn(500, 3, generator=torch.Generator().manual_seed(0)) * 5
    assert torch.allclose(ContractionBeyond(1.0)(x), SceneContraction(order=float("inf"))(x))


def test_linear_inside_the_radius_and_nerfstudios_contraction_of_x_over_radius_beyond() -> None:
    radius = 7.5
    x = (torch.rand(400, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1) * radius  # |x|∞ <= radius
    assert torch.allclose(ContractionBeyond(radius)(x), x / radius)
    far = torch.tensor([[3 * radius, 0.5, -2.0], [0.0, -10 * radius, radius]])
    expected = SceneContraction(order=float("inf"))(far / radius)
    assert torch.allclose(ContractionBeyond(radius)(far), expected)
    # the L∞ norm of the contracted point is 2 - radius / |x|∞ beyond the radius
    assert torch.allclose(ContractionBeyond(radius)(far).abs().amax(-1), 2 - radius / far.abs().amax(-1))


def test_continuous_at_the_radius_and_finite_within_the_grid_for_huge_inputs() -> None:
    radius = 4.0
    inside = torch.tensor([[radius * (1 - 1e-6), 0.3, 0.1]])
    outside = torch.tensor([[radius * (1 + 1e-6), 0.3, 0.1]])
    contraction = ContractionBeyond(radius)
    assert torch.allclose(contraction(inside), contraction(outside), atol=1e-5)
    huge = torch.tensor([[1e30, -1e30, 3.0], [-3e38, 0.0, 0.0]])
    contracted = contraction(huge)
    assert torch.isfinite(contracted).all() and bool((contracted.abs() <= 2).all())


def test_gaussian_means_follow_the_tensor_path() -> None:
    radius = 3.0
    mean = torch.tensor([[1.0, 2.0, -0.5], [9.0, 1.0, 0.0]])
    cov = torch.eye(3).expand(2, 3, 3) * 0.01
    # nerfstudio's Gaussian contraction needs the 2-norm (order None); the mean is the same map
    contraction = ContractionBeyond(radius)
    contraction.order = None
    out = contraction(Gaussians(mean=mean, cov=cov))
    assert torch.allclose(out.mean, SceneContraction()(mean / radius))
    assert torch.allclose(out.cov[0], cov[0] / radius**2)  # inside: only the scaling


@pytest.mark.parametrize("radius", [0.0, -1.0, math.inf, math.nan])
def test_bad_radius_is_refused(radius: float) -> None:
    with pytest.raises(ValueError, match="radius"):
        ContractionBeyond(radius)


def _cameras(camera_to_worlds: torch.Tensor, fx=1.0, fy=1.0, cx=1.0, cy=1.0, width=2, height=2) -> Cameras:
    n = camera_to_worlds.shape[0]
    full = lambda v: torch.full((n, 1), float(v))  # noqa: E731
    return Cameras(
        camera_to_worlds=camera_to_worlds.float(),
        fx=full(fx),
        fy=full(fy),
        cx=full(cx),
        cy=full(cy),
        width=full(width).long(),
        height=full(height).long(),
    )


def test_frustum_extent_of_an_axis_camera_is_the_far_corner() -> None:
    # fx = 1, a 2-pixel image centred: corners at (±1, ±1) per unit depth, so at depth 5 the
    # corners are (±5, ±5, -5) and the extent is 5; moved by 3 along x it is 8.
    identity = torch.eye(4)[:3][None]
    assert frustum_extent(_cameras(identity), 5.0) == pytest.approx(5.0)
    moved = identity.clone()
    moved[0, 0, 3] = 3.0
    assert frustum_extent(_cameras(moved), 5.0) == pytest.approx(8.0)


def test_frustum_extent_bounds_every_point_of_the_cut_frustum_and_is_reached() -> None:
    generator = torch.Generator().manual_seed(2)
    rotation, _ = torch.linalg.qr(torch.randn(3, 3, generator=generator))
    c2w = torch.cat([rotation, torch.tensor([[0.4], [-0.2], [0.9]])], dim=1)[None]
    cameras = _cameras(c2w, fx=80.0, fy=80.0, cx=50.0, cy=40.0, width=100, height=80)
    far = 6.0
    extent = frustum_extent(cameras, far)
    # random points of the frustum: pixel (u, v) at depth z <= far, in world coordinates
    u = torch.rand(20000, generator=generator) * 100
    v = torch.rand(20000, generator=generator) * 80
    z = torch.rand(20000, generator=generator) * far
    local = torch.stack([(u - 50) / 80 * z, -(v - 40) / 80 * z, -z], dim=-1)
    world = local @ rotation.T + c2w[0, :, 3]
    reached = world.abs().amax()
    assert float(reached) <= extent + 1e-5
    assert float(reached) > 0.97 * extent


def test_bad_far_depth_is_refused() -> None:
    with pytest.raises(ValueError, match="far depth"):
        frustum_extent(_cameras(torch.eye(4)[:3][None]), 0.0)


def test_the_model_contracts_beyond_the_extent_it_is_given() -> None:
    from tiny_training import tiny_model

    model = tiny_model(metadata={EXTENT_KEY: 12.0})
    assert model.contraction_radius == 12.0
    distortions = [model.field.spatial_distortion] + [net.spatial_distortion for net in model.proposal_networks]
    assert all(isinstance(d, ContractionBeyond) and d.radius == 12.0 for d in distortions)
    # a scene inside the unit cube keeps radius 1; without an extent: nerfacto's own contraction
    assert tiny_model(metadata={EXTENT_KEY: 0.5}).contraction_radius == 1.0
    for model in (tiny_model(),):
        assert model.contraction_radius == 1.0
        assert not isinstance(model.field.spatial_distortion, ContractionBeyond)


def test_clear_air_keeps_nerfactos_contraction_also_after_auto_chose_it_and_in_a_loaded_checkpoint() -> None:
    """``none`` contracts as nerfacto whatever the scene's extent; a medium model from the extent. An
    ``auto`` model that chose ``none`` switches at once, and a fresh ``auto`` model that loads its
    checkpoint (the viewer, ``ns-render``, a resumed run) takes nerfacto's contraction from it."""
    from tiny_training import tiny_model

    from seathru_nerfstudio.medium_field import MEDIUM_MODELS

    clear = tiny_model(metadata={EXTENT_KEY: 12.0}, medium_model="none")
    assert clear.contraction_radius == 1.0 and type(clear.field.spatial_distortion) is SceneContraction
    chosen = tiny_model(metadata={EXTENT_KEY: 12.0}, medium_model="auto")
    assert chosen.contraction_radius == 12.0
    chosen.medium_model_code.fill_(MEDIUM_MODELS.index("none"))
    chosen.fit_object_field_to_medium_model()
    assert chosen.contraction_radius == 1.0
    loaded = tiny_model(metadata={EXTENT_KEY: 12.0}, medium_model="auto")
    assert loaded.contraction_radius == 12.0
    loaded.load_state_dict(chosen.state_dict())
    assert loaded.medium_model == "none" and loaded.contraction_radius == 1.0
    distortions = [loaded.field.spatial_distortion] + [net.spatial_distortion for net in loaded.proposal_networks]
    assert all(type(d) is SceneContraction for d in distortions)
