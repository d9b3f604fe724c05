"""seathru-bench numerics: the closed-form references, the order estimate, and a small study."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from seathru_nerfstudio.bench import numerics
from seathru_nerfstudio.bench.numerics import NumericsConfig, Profile, exact_slabs, observed_order, render_profile
from seathru_nerfstudio.rendering import formation_model

WATER = dict(sigma_attn=(0.4, 0.3, 0.2), sigma_bs=(0.3, 0.25, 0.2), c_med=(0.07, 0.2, 0.39))


def test_exact_slabs_of_an_opaque_wall_is_the_seathru_formation_model():
    J = (0.8, 0.5, 0.3)
    wall = Profile("w", "", slabs=((2.0, math.inf, 1e9, J),), **WATER)
    expected = formation_model(
        torch.tensor(J, dtype=torch.float64),
        torch.tensor([2.0], dtype=torch.float64),
        torch.tensor(WATER["sigma_attn"], dtype=torch.float64),
        torch.tensor(WATER["sigma_bs"], dtype=torch.float64),
        torch.tensor(WATER["c_med"], dtype=torch.float64),
    )
    assert exact_slabs(wall) == pytest.approx(expected.numpy(), abs=1e-9)
    open_water = Profile("o", "", **WATER)
    assert exact_slabs(open_water) == pytest.approx(WATER["c_med"], abs=1e-15)


@pytest.mark.parametrize("quadrature", ["analytic"])
def test_analytic_quadrature_is_exact_when_the_edges_are_sample_boundaries(quadrature):
    # 0.05 + 39 * (5.95 / 119) = 2.0: the slab's edges fall on interval boundaries.
    slab = Profile("s", "", near=0.05, far=6.0, slabs=((2.0, 2.5, 30.0, (0.8, 0.5, 0.3)),), **WATER)
    rgb, _ = render_profile(slab, 119, quadrature, "mid")
    assert rgb[0].numpy() == pytest.approx(exact_slabs(slab), abs=1e-12)
    # ... which the paper's sums are not: they count the medium inside the slab's intervals.
    paper, _ = render_profile(slab, 119, "paper", "mid")
    assert float(np.max(np.abs(paper[0].numpy() - exact_slabs(slab)))) > 1e-4


def test_observed_order():
    ns = [8, 16, 32, 64, 128]
    assert observed_order(ns, [3.0 / n**2 for n in ns]) == pytest.approx(2.0)
    assert observed_order(ns, [0.5 / n for n in ns]) == pytest.approx(1.0)
    assert math.isinf(observed_order(ns, [1e-16] * 5))


def test_small_study_writes_table_plots_and_finds_the_expected_orders(tmp_path):
    config = NumericsConfig(
        output_dir=tmp_path,
        min_log2_samples=5,
        max_log2_samples=10,
        timing_max_log2_samples=6,
        timing_rays=16,
        timing_repeats=1,
        phases=2,
        profiles=("open-water", "smooth-blob", "behind-near"),
    )
    results = numerics.run_numerics(config)
    by_name = {p["profile"]: p["schemes"] for p in results["profiles"]}
    assert all(math.isinf(s["order"]) for s in by_name["open-water"].values())  # closed form: exact
    assert by_name["smooth-blob"]["analytic/mid"]["order"] == pytest.approx(2.0, abs=0.3)
    assert by_name["smooth-blob"]["paper/mid"]["order"] == pytest.approx(1.0, abs=0.3)
    # A surface right behind the near plane: the paper's sums overcount the medium there.
    assert by_name["behind-near"]["paper/mid"]["errors"][0] > 10 * by_name["behind-near"]["analytic/mid"]["errors"][0]
    saved = json.loads((tmp_path / "numerics.json").read_text())
    assert saved["samples"] == [2**k for k in range(5, 11)]
    table = (tmp_path / "numerics.md").read_text()
    assert "| smooth-blob | analytic/mid |" in table and "observed order" in table
    for kind in ("samples", "time"):
        assert (tmp_path / f"bench_numerics_{kind}.png").read_bytes().startswith(b"\x89PNG")
