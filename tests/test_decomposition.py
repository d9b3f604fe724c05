"""The decomposition moves the right way on a tiny water scene (issue 8).

One short ``seathru-bench`` run of ``seathru-nerf-lite`` with its default settings (the
veiling-light and geometry stage and the medium fit moved earlier) on a 48x36 synthetic water scene, evaluated just after
the object field starts and at the end. Loose bounds that fit CI's time: the clean image's error
falls, the surfaces are at their depth, the veiling light moves toward the truth, open water stays
empty, and the medium's densities stay in a physical range. The full-size figures are in
docs/benchmarks.md.

It runs on one torch thread, where a run with a given seed repeats exactly (the rays follow the
seed: ``data/seeded_sampler.py``); on two threads the order of floating-point sums varies, and the
losses of two runs of one seed part in the 8th digit after about 20 steps.
"""

from __future__ import annotations

import pytest

from tiny_training import DECOMPOSITION_ITERATIONS as ITERATIONS


@pytest.fixture(scope="module")
def run(decomposition_run):
    """The first and the last evaluation of the decomposition check's bench run (conftest)."""
    assert decomposition_run["failures"] == []
    (seathru,) = decomposition_run["runs"]
    return seathru["evals"][0], seathru["evals"][-1]


@pytest.mark.slow
def test_clean_error_falls_and_the_surfaces_are_at_their_depth(run):
    """The clean image improves once the object colour learns, and the surfaces move to their
    depth. Without the medium fit the rise on this tiny scene was small and depended on the seed:
    +0.78, +1.16 and +0.45 dB for seeds 42, 7 and 3 on one thread (2026-11-25, 0729532); with the excess
    term and no fit it fell (-1.6 dB). With both, seed 42: +3.3 dB (12.9 -> 16.2, 2026-11-26, f139320).
    The margin stays 0.3 dB; the full-size figures are in docs/benchmarks.md, their history in
    docs/history.md. The mean depth error falls; it used to halve, from an early state whose object
    colour had died at entry. Since the backscatter is capped at entry (43bf02e, 2026-11-27) the colour
    lives and the early error is already low: 0.283 -> 0.174 (clean 10.4 -> 19.4 dB), seed 42."""
    early, late = run
    assert late["step"] == ITERATIONS
    assert late["metrics"]["clean_psnr"] > early["metrics"]["clean_psnr"] + 0.3, (early["metrics"], late["metrics"])
    assert late["metrics"]["depth_abs_rel"] < early["metrics"]["depth_abs_rel"], (early["metrics"], late["metrics"])
    assert late["metrics"]["depth_abs_rel_median"] < 0.2, late["metrics"]


@pytest.mark.slow
def test_the_veiling_light_is_the_open_waters_from_entry_and_stays(run):
    """At the end of the first stage the veiling light becomes the colour of the rays the SfM geometry
    leaves open, and is held: within 10% of the truth just after entry and unchanged at the end.
    Learned on instead, it reached the truth only after the fit, with the open water filled up to then
    (2026-11-28; docs/history.md)."""
    early, late = run
    assert early["medium_error"]["B_inf"]["rel_mean"] < 0.1, early["medium_error"]["B_inf"]
    assert late["medium_error"]["B_inf"]["pred"] == pytest.approx(early["medium_error"]["B_inf"]["pred"], rel=1e-6)


@pytest.mark.slow
def test_auto_keeps_a_coloured_medium_in_water(run):
    """``auto`` decides at the fit's step, as in the defaults (both at 500), and keeps water's medium."""
    early, late = run
    assert early["medium_model"] == "seathru"  # undecided renders seathru
    assert late["medium_model"] in ("seathru", "uniform")


@pytest.mark.slow
def test_open_water_stays_empty_and_the_medium_stays_physical(run):
    _, late = run
    assert late["metrics"]["open_water_accumulation"] < 0.2
    for key in ("beta_D", "beta_B"):
        # within a factor 4 of the truth (1/m): no veil in front of the lens, no clear water
        for predicted, true in zip(late["medium_error"][key]["pred"], late["medium_error"][key]["true"]):
            assert true / 4 < predicted < 4 * true, (key, late["medium_error"][key])
