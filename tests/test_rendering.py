"""The renderer against closed forms, limits, finite differences and stiff inputs."""

from __future__ import annotations

import itertools

import pytest
import torch

from seathru_nerfstudio.rendering import absorbed_fraction, depth_lit_backscatter_density, formation_model, object_weights, render_seathru



@pytest.fixture(autouse=True)
def float64_by_default():
    """Reference maths in float64, restored afterwards (other modules expect float32)."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


BETA_D = torch.tensor([1.3, 1.2, 0.9], dtype=torch.float64)
BETA_B = torch.tensor([0.95, 0.85, 0.7], dtype=torch.float64)
B_INF = torch.tensor([0.07, 0.2, 0.39], dtype=torch.float64)
J = torch.tensor([0.8, 0.5, 0.3], dtype=torch.float64)


def uneven_bins(num: int, near: float, far: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Contiguous bins with random widths from ``near`` to ``far``: starts and deltas ``[num, 1]``."""
    gen = torch.Generator().manual_seed(seed)
    widths = torch.rand(num, generator=gen) ** 3 + 1e-3
    edges = torch.cat([torch.zeros(1), torch.cumsum(widths, 0)])
    edges = near + (far - near) * edges / edges[-1]
    return edges[:-1, None], (edges[1:] - edges[:-1])[:, None]


def wall_ray(starts: torch.Tensor, deltas: torch.Tensor, k: int, wall_density: float = 1e12):
    """An opaque wall filling bin ``k`` (its front face at ``starts[k]``), empty elsewhere."""
    num = starts.shape[0]
    density = torch.zeros(num, 1)
    density[k:] = wall_density
    rgb = torch.rand(num, 3, generator=torch.Generator().manual_seed(k))
    rgb[k] = J
    return rgb, density


def render(rgb, density, starts, deltas, c_med=B_INF, attn=BETA_D, bs=BETA_B, quadrature="analytic"):
    return render_seathru(rgb, density, starts, deltas, c_med, attn, bs, quadrature=quadrature)


@pytest.mark.parametrize("num_samples", [1, 2, 7, 48, 300])
@pytest.mark.parametrize("far", [3.0, 1e3, 1e6])
def test_opaque_wall_reduces_to_seathru_formation_model(num_samples, far):
    starts, deltas = uneven_bins(num_samples, near=0.05, far=far, seed=num_samples)
    for k in range(num_samples):
        rgb, density = wall_ray(starts, deltas, k)
        out = render(rgb, density, starts, deltas)
        z = starts[k]
        expected_direct = J * torch.exp(-BETA_D * z)
        expected_bs = B_INF * -torch.expm1(-BETA_B * z)
        torch.testing.assert_close(out.direct, expected_direct, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(out.backscatter, expected_bs, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(out.rgb, formation_model(J, z, BETA_D, BETA_B, B_INF), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(out.clean, J, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(out.accumulation, torch.ones(1))


def test_paper_quadrature_counts_the_medium_inside_the_wall_bin():
    """The printed sec. 4.3 sums see backscatter up to the wall's far face, z + delta_k."""
    starts, deltas = uneven_bins(20, near=0.1, far=4.0, seed=3)
    k = 11
    rgb, density = wall_ray(starts, deltas, k)
    out = render(rgb, density, starts, deltas, quadrature="paper")
    z, delta = starts[k], deltas[k]
    torch.testing.assert_close(out.direct, J * torch.exp(-BETA_D * z))
    torch.testing.assert_close(out.backscatter, B_INF * -torch.expm1(-BETA_B * (z + delta)))


def test_ray_that_hits_nothing_shows_the_veiling_light():
    for near, far, num in [(0.0, 1.0, 4), (0.05, 1e3, 64), (2.0, 1e6, 17)]:
        starts, deltas = uneven_bins(num, near, far, seed=num)
        rgb = torch.rand(num, 3)
        out = render(rgb, torch.zeros(num, 1), starts, deltas)
        torch.testing.assert_close(out.backscatter, B_INF, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(out.direct, torch.zeros(3))
        torch.testing.assert_close(out.clean, torch.zeros(3))
        torch.testing.assert_close(out.accumulation, torch.zeros(1))


def test_clear_air_reproduces_nerfstudio_rendering():
    from nerfstudio.cameras.rays import Frustums, RaySamples
    from nerfstudio.model_components.renderers import RGBRenderer

    gen = torch.Generator().manual_seed(0)
    batch, num = 5, 32
    starts, deltas = uneven_bins(num, 0.05, 6.0, seed=1)
    starts, deltas = starts.expand(batch, num, 1), deltas.expand(batch, num, 1)
    rgb = torch.rand(batch, num, 3, generator=gen)
    density = torch.rand(batch, num, 1, generator=gen) * 5.0
    zeros = torch.zeros(batch, 3)
    samples = RaySamples(
        frustums=Frustums(
            origins=torch.zeros(batch, num, 3),
            directions=torch.ones(batch, num, 3) / 3**0.5,
            starts=starts,
            ends=starts + deltas,
            pixel_area=torch.ones(batch, num, 1),
        ),
        deltas=deltas,
    )
    weights = samples.get_weights(density)
    expected = RGBRenderer(background_color="black")(rgb=rgb, weights=weights)
    for quadrature in ("analytic", "paper"):
        out = render(rgb, density, starts, deltas, c_med=torch.rand(batch, 3), attn=zeros, bs=zeros, quadrature=quadrature)
        torch.testing.assert_close(out.rgb, expected)
        torch.testing.assert_close(out.clean, expected)
        torch.testing.assert_close(out.weights, weights)
        torch.testing.assert_close(out.backscatter, torch.zeros(batch, 3))


def test_paper_quadrature_matches_the_printed_equations():
    """An independent per-sample loop over sec. 4.3's equations, plus our head and tail."""
    gen = torch.Generator().manual_seed(4)
    num = 9
    starts, deltas = uneven_bins(num, 0.3, 5.0, seed=2)
    rgb = torch.rand(num, 3, generator=gen)
    density = torch.rand(num, 1, generator=gen) * 2
    c_med, attn, bs = torch.rand(3, generator=gen), torch.rand(3, generator=gen), torch.rand(3, generator=gen)
    direct = torch.zeros(3)
    backscatter = (1 - torch.exp(-bs * starts[0])) * c_med
    tau = 0.0
    for i in range(num):
        t_obj = torch.exp(torch.tensor(-tau))
        s, d, sig = starts[i], deltas[i], density[i]
        direct = direct + t_obj * torch.exp(-attn * s) * (1 - torch.exp(-sig * d)) * rgb[i]
        backscatter = backscatter + t_obj * torch.exp(-bs * s) * (1 - torch.exp(-bs * d)) * c_med
        tau += float(sig * d)
    backscatter = backscatter + torch.exp(torch.tensor(-tau)) * torch.exp(-bs * (starts[-1] + deltas[-1])) * c_med
    out = render(rgb, density, starts, deltas, c_med, attn, bs, quadrature="paper")
    torch.testing.assert_close(out.direct, direct)
    torch.testing.assert_close(out.backscatter, backscatter)


def test_analytic_quadrature_is_invariant_to_splitting_bins():
    """Exact for piecewise-constant rays: cutting every bin in two changes nothing."""
    gen = torch.Generator().manual_seed(5)
    num = 12
    starts, deltas = uneven_bins(num, 0.2, 4.0, seed=7)
    rgb = torch.rand(num, 3, generator=gen)
    density = torch.rand(num, 1, generator=gen) * 10
    c_med, attn, bs = torch.rand(3, generator=gen), torch.rand(3, generator=gen) * 2, torch.rand(3, generator=gen)
    frac = torch.rand(num, 1, generator=gen) * 0.8 + 0.1
    split_starts = torch.stack([starts, starts + frac * deltas], 1).reshape(-1, 1)
    split_deltas = torch.stack([frac * deltas, (1 - frac) * deltas], 1).reshape(-1, 1)
    twice = lambda t: t.repeat_interleave(2, dim=0)  # noqa: E731
    coarse = render(rgb, density, starts, deltas, c_med, attn, bs)
    fine = render(twice(rgb), twice(density), split_starts, split_deltas, c_med, attn, bs)
    for name in ("rgb", "direct", "backscatter", "clean", "accumulation"):
        torch.testing.assert_close(getattr(fine, name), getattr(coarse, name), rtol=1e-11, atol=1e-13)
    paper_coarse = render(rgb, density, starts, deltas, c_med, attn, bs, quadrature="paper")
    paper_fine = render(twice(rgb), twice(density), split_starts, split_deltas, c_med, attn, bs, quadrature="paper")
    assert not torch.allclose(paper_fine.rgb, paper_coarse.rgb, rtol=1e-6)


def test_paper_quadrature_converges_to_analytic_with_refinement():
    """Both integrate the same ray; the paper's sums converge to it at first order."""
    gen = torch.Generator().manual_seed(6)
    c_med, attn, bs = torch.rand(3, generator=gen), torch.rand(3, generator=gen), torch.rand(3, generator=gen)
    errors = []
    for num in (16, 64, 256, 1024):
        starts = torch.linspace(0.1, 3.0, num + 1)[:-1, None]
        deltas = torch.full_like(starts, 2.9 / num)
        mid = starts + deltas / 2
        density = 3.0 * torch.exp(-((mid - 1.5) ** 2) / 0.05)
        rgb = torch.cat([torch.sin(mid) ** 2, torch.cos(mid) ** 2, 0.5 * torch.ones_like(mid)], -1)
        a = render(rgb, density, starts, deltas, c_med, attn, bs).rgb
        p = render(rgb, density, starts, deltas, c_med, attn, bs, quadrature="paper").rgb
        errors.append(float((a - p).abs().max()))
    orders = [torch.log2(torch.tensor(errors[i] / errors[i + 1])) / 2 for i in range(len(errors) - 1)]
    assert all(0.8 < float(o) < 1.2 for o in orders), (errors, orders)


@pytest.mark.parametrize("quadrature", ["analytic", "paper"])
def test_gradients_match_finite_differences(quadrature):
    gen = torch.Generator().manual_seed(8)
    num = 6
    starts, deltas = uneven_bins(num, 0.1, 3.0, seed=9)
    rgb = torch.rand(2, num, 3, generator=gen).requires_grad_()
    # densities straddle the series threshold of absorbed_fraction (x ~ 1e-3)
    density = torch.tensor([1e-4, 5e-4, 2e-3, 0.3, 4.0, 1e-5]).expand(2, num)[..., None]
    density = (density * (1 + 0.1 * torch.rand(2, num, 1, generator=gen))).requires_grad_()
    c_med = torch.rand(2, 3, generator=gen).requires_grad_()
    attn = (torch.rand(2, 3, generator=gen) * 0.5).requires_grad_()
    bs = (torch.rand(2, 3, generator=gen) * 0.5).requires_grad_()

    def f(rgb, density, c_med, attn, bs):
        out = render(rgb, density, starts.expand(2, num, 1), deltas.expand(2, num, 1), c_med, attn, bs, quadrature)
        return out.rgb, out.clean, out.backscatter

    assert torch.autograd.gradcheck(f, (rgb, density, c_med, attn, bs), eps=1e-7, atol=1e-6)


def test_absorbed_fraction_is_continuous_across_its_series_switch():
    sigma_total = torch.logspace(-6, 0, 2001)
    delta = torch.full_like(sigma_total, 1e-2)  # x = sigma * delta crosses 1e-3
    got = absorbed_fraction(0.5 * sigma_total, sigma_total, delta)
    exact = 0.5 * -torch.expm1(-sigma_total * delta)
    torch.testing.assert_close(got, exact, rtol=1e-10, atol=0)


STIFF_OBJ_OPTICAL_DEPTH = [0.0, 1e-12, 1e-3, 1.0, 1e3, 1e10]
STIFF_MEDIUM = [0.0, 1e-9, 1e3]
STIFF_DELTA = [1e-9, 1e-3, 1.0, 1e6]


@pytest.mark.parametrize("quadrature", ["analytic", "paper"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_stiff_and_extreme_inputs_stay_finite_and_in_range(quadrature, dtype):
    cases = list(itertools.product(STIFF_OBJ_OPTICAL_DEPTH, STIFF_MEDIUM, STIFF_DELTA))
    num = 8
    batch = len(cases)
    tau = torch.tensor([c[0] for c in cases], dtype=dtype)
    sigma_med = torch.tensor([c[1] for c in cases], dtype=dtype)
    delta = torch.tensor([c[2] for c in cases], dtype=dtype)
    deltas = delta[:, None, None].expand(batch, num, 1).clone()
    # s reaches 1e6 and beyond: starts at 1e6 - num * delta or at 0
    near = torch.where(delta < 1.0, torch.full_like(delta, 1e6), torch.zeros_like(delta))
    starts = near[:, None, None] + torch.arange(num, dtype=dtype)[None, :, None] * deltas
    density = (tau / delta)[:, None, None].expand(batch, num, 1).clone()
    density[:, :3] = 0.0  # open medium first, then the stiff object
    density.requires_grad_()
    rgb = torch.rand(batch, num, 3, dtype=dtype).requires_grad_()
    c_med = torch.rand(batch, 3, dtype=dtype).requires_grad_()
    attn = sigma_med[:, None].expand(batch, 3).clone().requires_grad_()
    bs = (sigma_med[:, None].expand(batch, 3) * 0.7).clone().requires_grad_()
    out = render_seathru(rgb, density, starts, deltas, c_med, attn, bs, quadrature=quadrature)
    for name in ("rgb", "direct", "backscatter", "clean", "accumulation", "weights", "transmittance"):
        value = getattr(out, name)
        assert torch.isfinite(value).all(), name
        assert (value >= 0).all(), name
        assert (value <= 1 + 1e-5).all() or name == "rgb", name
    assert (out.rgb <= 2).all()
    # Under the analytic quadrature light is conserved per channel when sigma_attn == sigma_bs.
    if quadrature == "analytic":
        same = render_seathru(rgb, density, starts, deltas, torch.ones_like(c_med), bs, bs, quadrature=quadrature)
        assert (same.direct / rgb.max() + same.backscatter <= 1 + 1e-5).all()
    loss = out.rgb.sum() + out.clean.sum() + out.backscatter.sum() + out.transmittance.sum()
    grads = torch.autograd.grad(loss, (rgb, density, c_med, attn, bs))
    for g in grads:
        assert torch.isfinite(g).all()


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_half_precision_autocast_inputs_stay_finite(half):
    batch, num = 64, 16
    gen = torch.Generator().manual_seed(11)
    starts, deltas = uneven_bins(num, 0.05, 1e4, seed=12)
    starts = starts.expand(batch, num, 1).to(half)
    deltas = deltas.expand(batch, num, 1).to(half)
    density = (10 ** (torch.rand(batch, num, 1, generator=gen) * 8 - 2)).to(half)  # up to 6e4 (fp16 max)
    rgb = torch.rand(batch, num, 3, generator=gen).to(half).requires_grad_()
    density.requires_grad_()
    c_med = torch.rand(batch, 3, generator=gen).to(half)
    attn = (torch.rand(batch, 3, generator=gen) * 1e3).to(half).requires_grad_()
    bs = (torch.rand(batch, 3, generator=gen)).to(half)
    with torch.autocast(device_type="cpu", dtype=half):
        out = render_seathru(rgb, density, starts, deltas, c_med, attn, bs)
        loss = (out.rgb.sum() + out.clean.sum()) * 1e3
    assert out.rgb.dtype == torch.float32
    for name in ("rgb", "direct", "backscatter", "clean", "accumulation"):
        assert torch.isfinite(getattr(out, name)).all(), name
    grads = torch.autograd.grad(loss, (rgb, density, attn))
    for g in grads:
        assert torch.isfinite(g.float()).all()


def test_formation_model_at_infinite_range_is_the_veiling_light():
    depth = torch.tensor([[0.0], [1.0], [float("inf")]])
    out = formation_model(J.expand(3, 3), depth, BETA_D, BETA_B, B_INF)
    torch.testing.assert_close(out[0], J)
    torch.testing.assert_close(out[1], J * torch.exp(-BETA_D) + B_INF * (1 - torch.exp(-BETA_B)))
    torch.testing.assert_close(out[2], B_INF)


def test_object_weights_are_nerfstudios_and_the_renderers():
    """The object alone: nerfstudio's weights, T_0 = 1, w_i = T_i - T_{i+1}, the renderer's own
    weights and accumulation; finite for stiff densities and under half-precision autocast."""
    from nerfstudio.cameras.rays import Frustums, RaySamples

    gen = torch.Generator().manual_seed(3)
    batch, num = 4, 24
    starts, deltas = uneven_bins(num, 0.1, 5.0, seed=2)
    starts, deltas = starts.expand(batch, num, 1), deltas.expand(batch, num, 1)
    density = torch.rand(batch, num, 1, generator=gen) * 4.0
    samples = RaySamples(
        frustums=Frustums(
            origins=torch.zeros(batch, num, 3), directions=torch.ones(batch, num, 3) / 3**0.5,
            starts=starts, ends=starts + deltas, pixel_area=torch.ones(batch, num, 1),
        ),
        deltas=deltas,
    )  # fmt: skip
    weights, transmittance, tau = object_weights(density, deltas)
    torch.testing.assert_close(weights, samples.get_weights(density))
    assert torch.all(transmittance[:, 0] == 1) and tau.shape == (batch, num + 1, 1)
    torch.testing.assert_close(weights[:, :-1], transmittance[:, :-1] - transmittance[:, 1:])
    out = render(torch.rand(batch, num, 3, generator=gen), density, starts, deltas)
    torch.testing.assert_close(out.weights, weights)
    torch.testing.assert_close(out.accumulation, -torch.expm1(-tau[:, -1]))

    stiff = torch.tensor([0.0, 1e30, float("inf"), 1e-30])[None, :, None]
    w, t, _ = object_weights(stiff, torch.tensor([1.0, 1e-9, 1.0, 1e30])[None, :, None])
    assert torch.isfinite(w).all() and torch.isfinite(t).all()
    for half in (torch.float16, torch.bfloat16):
        with torch.autocast(device_type="cpu", dtype=half):
            w, t, _ = object_weights(torch.full((2, 8, 1), 6e4).to(half), torch.full((2, 8, 1), 1e3).to(half))
        assert w.dtype == torch.float32 and torch.isfinite(w).all() and torch.isfinite(t).all()


@pytest.mark.parametrize("quadrature", ["analytic", "paper"])
def test_veil_from_open_rays_keeps_values_and_scales_the_veil_gradient_by_the_open_share(quadrature):
    """Same image; d rgb / d c_med is the backscatter's own factor times T_obj,N, ray by ray: 1 on an
    empty ray, 0 behind an opaque wall; the densities' and the object's gradients are unchanged."""
    starts, deltas = uneven_bins(32, 0.1, 12.0, seed=3)
    gen = torch.Generator().manual_seed(5)
    rgb = torch.rand(3, 32, 3, generator=gen)
    density = torch.rand(3, 32, 1, generator=gen) * 0.3
    density[1] = 0.0  # open water
    density[2, 20:] = 1e12  # an opaque wall
    grads = {}
    for flag in (False, True):
        c_med = B_INF.expand(3, 3).clone().requires_grad_(True)
        attn = BETA_D.expand(3, 3).clone().requires_grad_(True)
        bs = BETA_B.expand(3, 3).clone().requires_grad_(True)
        obj = rgb.clone().requires_grad_(True)
        out = render_seathru(obj, density, starts.expand(3, 32, 1), deltas.expand(3, 32, 1), c_med, attn, bs,
                             quadrature=quadrature, veil_from_open_rays=flag)
        out.rgb.sum().backward()
        grads[flag] = (out, c_med.grad, attn.grad, bs.grad, obj.grad)
    plain, veil_open = grads[False], grads[True]
    torch.testing.assert_close(veil_open[0].rgb, plain[0].rgb, rtol=1e-14, atol=1e-15)
    for a, b in zip(veil_open[2:], plain[2:]):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)
    open_share = 1.0 - veil_open[0].accumulation  # T_obj,N
    torch.testing.assert_close(veil_open[1], plain[1] * open_share, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(veil_open[1][1], torch.ones(3), rtol=1e-12, atol=1e-15)  # empty: sees B_inf
    torch.testing.assert_close(veil_open[1][2], torch.zeros(3), rtol=0, atol=1e-12)  # behind the wall
    assert (veil_open[1][0] > 0).all() and (veil_open[1][0] < plain[1][0]).all()


@pytest.mark.parametrize("up", [0.05, 0.2, 0.6])
def test_depth_lit_backscatter_is_the_integral_of_light_growing_along_the_ray(up):
    """Light growing as ``e^{kappa u t}`` along the ray (``kappa`` per unit length, ``u`` the sin of the
    elevation) gives, in front of an opaque wall at ``z``, ``B∞ ∫_0^z sigma e^{-sigma t} e^{kappa u t} dt``
    (trapezoid sum on a fine grid) and, on an open ray, ``B∞ sigma / (sigma - kappa u)``: the renderer
    with the veil ``B∞ G``, ``G = sigma / (sigma - kappa u)``, and ``veil_gain = G``. Its slope at the
    camera is the level veil's; without ``veil_gain`` the wall's backscatter is ``G`` times too bright."""
    kappa = 0.8 * BETA_B  # the light's attenuation with depth, per unit length, below sigma_bs
    gain = BETA_B / (BETA_B - kappa * up)
    starts, deltas = uneven_bins(40, near=0.05, far=6.0, seed=3)
    for k in (0, 5, 20, 39):
        rgb, density = wall_ray(starts, deltas, k)
        z = float(starts[k])
        t = torch.linspace(0.0, z, 200001)[:, None]
        integrand = BETA_B * torch.exp(-(BETA_B - kappa * up) * t)
        expected = B_INF * torch.trapezoid(integrand, t, dim=0)
        out = render_seathru(rgb, density, starts, deltas, B_INF * gain, BETA_D, BETA_B, veil_gain=gain)
        torch.testing.assert_close(out.backscatter, expected, rtol=1e-8, atol=1e-12)
        torch.testing.assert_close(out.direct, J * torch.exp(-BETA_D * z), rtol=1e-10, atol=1e-12)
        plain = render_seathru(rgb, density, starts, deltas, B_INF * gain, BETA_D, BETA_B)
        torch.testing.assert_close(plain.backscatter, gain * B_INF * -torch.expm1(-BETA_B * z), rtol=1e-10, atol=1e-12)
    empty = torch.zeros(40, 1)
    open_ray = render_seathru(torch.zeros(40, 3), empty, starts, deltas, B_INF * gain, BETA_D, BETA_B, veil_gain=gain)
    torch.testing.assert_close(open_ray.backscatter, B_INF * BETA_B / (BETA_B - kappa * up), rtol=1e-10, atol=1e-12)
    near = torch.tensor([[1e-4]]), torch.tensor([[1e-4]])
    wall = render_seathru(J[None], torch.full((1, 1), 1e12), near[0], near[1], B_INF * gain, BETA_D, BETA_B, veil_gain=gain)
    torch.testing.assert_close(wall.backscatter / 1e-4, B_INF * BETA_B, rtol=1e-3, atol=0.0)  # the level rate


def test_depth_lit_backscatter_density_never_raises_the_density_and_stays_finite():
    """``G`` below 1 is read as 1 (the veil never falls); huge and zero gains give finite densities."""
    sigma = torch.tensor([0.5, 0.2, 1e-3])
    torch.testing.assert_close(depth_lit_backscatter_density(sigma, torch.tensor([0.5, 1.0, 2.0])), sigma / torch.tensor([1.0, 1.0, 2.0]))
    extreme = depth_lit_backscatter_density(sigma.float(), torch.tensor([0.0, float("1e38"), 3e38]))
    assert bool(torch.isfinite(extreme).all()) and bool((extreme >= 0).all())


@pytest.mark.parametrize("quadrature", ["analytic", "paper"])
def test_surface_veil_saturates_surfaces_at_its_share_and_leaves_open_water_at_the_veil(quadrature):
    """``surface_veil = r``: an opaque wall at ``z`` shows ``r B∞ (1 − e^{−β_B z})`` behind ``J e^{−β_D z}``
    (the formation model with the veil ``r B∞``), an empty ray ``B∞``, and a half-transparent ray
    ``r`` times the one-veil backscatter plus ``(1 − r) B∞ T_obj,N``; ``r = 1`` is the one-veil render exactly."""
    share = torch.tensor([0.8, 0.92, 1.0])
    starts, deltas = uneven_bins(40, near=0.05, far=30.0, seed=4)
    for k in (0, 7, 25, 39):
        rgb, density = wall_ray(starts, deltas, k)
        out = render_seathru(rgb, density, starts, deltas, B_INF, BETA_D, BETA_B, quadrature=quadrature, surface_veil=share)
        z = starts[k] + (deltas[k] if quadrature == "paper" else 0.0)
        torch.testing.assert_close(out.backscatter, share * B_INF * -torch.expm1(-BETA_B * z), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(out.direct, J * torch.exp(-BETA_D * starts[k]), rtol=1e-10, atol=1e-12)
    empty = render_seathru(torch.rand(40, 3), torch.zeros(40, 1), starts, deltas, B_INF, BETA_D, BETA_B, quadrature=quadrature, surface_veil=share)
    torch.testing.assert_close(empty.backscatter, B_INF, rtol=1e-12, atol=1e-14)
    haze = torch.full((40, 1), 0.01)
    one_veil = render_seathru(torch.rand(40, 3), haze, starts, deltas, B_INF, BETA_D, BETA_B, quadrature=quadrature)
    two = render_seathru(torch.rand(40, 3), haze, starts, deltas, B_INF, BETA_D, BETA_B, quadrature=quadrature, surface_veil=share)
    open_share = 1.0 - one_veil.accumulation
    assert 0.5 < float(open_share) < 0.9
    torch.testing.assert_close(two.backscatter, share * one_veil.backscatter + (1 - share) * B_INF * open_share, rtol=1e-12, atol=1e-14)
    same = render_seathru(torch.rand(40, 3), haze, starts, deltas, B_INF, BETA_D, BETA_B, quadrature=quadrature, surface_veil=torch.ones(3))
    assert torch.equal(same.backscatter, one_veil.backscatter)


def test_surface_veil_gradient_reaches_the_object_density_through_the_open_share():
    """The open water's excess ``(1 − r) B∞ e^{−τ_N}`` is part of the image: a finite difference of a
    bin's density matches autograd, with ``r < 1``."""
    starts, deltas = uneven_bins(12, near=0.1, far=8.0, seed=9)
    density = torch.full((12, 1), 0.05).requires_grad_(True)
    rgb = torch.rand(12, 3, generator=torch.Generator().manual_seed(2))
    share = torch.tensor([0.7, 0.9, 0.95])

    def image(d):
        return render_seathru(rgb, d, starts, deltas, B_INF, BETA_D, BETA_B, surface_veil=share).rgb.sum()

    image(density).backward()
    h = 1e-6
    for i in (0, 6, 11):
        bumped_up, bumped_down = density.detach().clone(), density.detach().clone()
        bumped_up[i] += h
        bumped_down[i] -= h
        numeric = (image(bumped_up) - image(bumped_down)) / (2 * h)
        torch.testing.assert_close(density.grad[i, 0], numeric, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_surface_veil_stays_finite_on_extreme_inputs(dtype):
    """Densities, ranges and shares at the ends of what the format holds (finite inputs, as the renderer promises)."""
    starts, deltas = uneven_bins(16, near=0.0, far=6e4, seed=1)
    density = torch.tensor([0.0, 6e4, 3.0, 1e-7] * 4)[:, None].to(dtype)
    share = torch.tensor([0.0, 0.5, 1.0]).to(dtype)
    out = render_seathru(torch.rand(16, 3).to(dtype), density, starts.to(dtype), deltas.to(dtype), B_INF.to(dtype),
                         torch.tensor([0.0, 1e4, 1e-6]).to(dtype), torch.tensor([1e4, 0.0, 1e-6]).to(dtype), surface_veil=share)
    assert bool(torch.isfinite(out.rgb).all()) and bool((out.backscatter >= 0).all())
