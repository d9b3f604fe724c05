"""The ceiling (bench/ceiling.py, bench/ceiling_scene.py): the formation model inverted with the
true range and the best-fitting medium, and its place in seathru-bench's scores and report."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
import torch

from seathru_nerfstudio import metrics
from seathru_nerfstudio.bench import ceiling, report, scoring

WATER = {"beta_D": np.array([1.3, 1.2, 0.9]), "beta_B": np.array([0.95, 0.85, 0.7]), "B_inf": np.array([0.07, 0.2, 0.39])}
Q = 1.0 / 65535.0  # one step of a 16-bit image


def _drawn(n: int, seed: int, z_max: float = 6.0):
    """``n`` object pixels drawn with the formation model itself: (I, J, z), float64."""
    rng = np.random.default_rng(seed)
    J = rng.uniform(0.05, 0.95, (n, 3))
    z = rng.uniform(0.5, z_max, n)
    return ceiling.form_image(J, z, **WATER), J, z


# ---------------------------------------------------------------- the maths


def test_inversion_with_the_true_medium_is_exact_and_the_psnr_code_agrees():
    I, J, z = _drawn(4000, 0)
    J_hat, capped = ceiling.invert(I, z, **WATER)
    assert capped == 0 and np.max(np.abs(J_hat - J)) < 1e-12
    scores = metrics.clean_psnrs(torch.from_numpy(J_hat[None]), torch.from_numpy(J[None]), torch.from_numpy(z[None, :, None]))
    assert scores["clean_psnr_objects"] > 120 and scores["clean_psnr_near_third"] > 120  # float32 rounding only


def test_fit_recovers_backscatter_and_veil_from_formula_drawn_pixels():
    I, J, z = _drawn(20000, 1)
    fit = ceiling.fit_backscatter(I, J, z, WATER["beta_D"])
    np.testing.assert_allclose(fit.beta_B, WATER["beta_B"], rtol=1e-6)
    np.testing.assert_allclose(fit.B_inf, WATER["B_inf"], rtol=1e-6)
    assert max(fit.rms) < 1e-9 and fit.beta_D == tuple(WATER["beta_D"]) and fit.num_pixels == 20000
    # all three, from a fit made at a beta_D 20% off
    start = ceiling.fit_backscatter(I, J, z, 1.2 * WATER["beta_D"])
    assert max(abs(a / b - 1) for a, b in zip(start.beta_B, WATER["beta_B"])) > 1e-3  # the start is wrong
    full = ceiling.fit_medium(I, J, z, start)
    for key in ("beta_D", "beta_B", "B_inf"):
        np.testing.assert_allclose(getattr(full, key), WATER[key], rtol=1e-6)


def test_fit_of_clear_air_is_no_medium_and_its_ceiling_is_the_image():
    rng = np.random.default_rng(2)
    J, z = rng.uniform(0, 1, (500, 3)), rng.uniform(0.5, 5, 500)
    fit = ceiling.fit_backscatter(J, J, z, np.zeros(3))
    assert fit.B_inf == (0.0, 0.0, 0.0) and fit.rms == (0.0, 0.0, 0.0)  # beta_B: any, nothing scatters
    J_hat, _ = ceiling.invert(J, z, np.zeros(3), np.zeros(3), np.zeros(3))
    assert np.array_equal(J_hat, J)


def test_ceiling_falls_monotonically_with_the_noise():
    (I_fit, J_fit, z_fit), (I_test, J_test, z_test) = _drawn(20000, 3), _drawn(5000, 4)
    rng = np.random.default_rng(5)
    noise_fit, noise_test = rng.standard_normal(I_fit.shape), rng.standard_normal(I_test.shape)
    scores = []
    for sigma in (0.0, 1e-4, 1e-3, 1e-2, 3e-2):
        fit = ceiling.fit_backscatter(I_fit + sigma * noise_fit, J_fit, z_fit, WATER["beta_D"])
        J_hat, _ = ceiling.invert(I_test + sigma * noise_test, z_test, fit.beta_D, fit.beta_B, fit.B_inf)
        got = metrics.clean_psnrs(torch.from_numpy(J_hat), torch.from_numpy(J_test), torch.from_numpy(z_test[:, None]))
        scores.append((got["clean_psnr_objects"], got["clean_psnr_near_third"]))
    for key in (0, 1):
        assert all(a[key] > b[key] for a, b in zip(scores, scores[1:])), scores
    assert all(near > objects for objects, near in scores[1:])  # the near third is amplified least


def test_nearest_third_mask_is_exactly_the_nearest_third_of_object_pixels():
    n = 60  # object pixels, ranges a permutation of 1..n; plus open water
    ranges = torch.cat([torch.randperm(n, generator=torch.Generator().manual_seed(0)).float() + 1, torch.full((12,), math.inf)])
    z = ranges.reshape(8, 9, 1)
    mask = metrics.near_third_mask(z)
    assert torch.equal(mask, z <= n / 3) and int(mask.sum()) == n // 3
    for m in (1, 2, 4, 7):  # not divisible by 3: ceil(m / 3) pixels, the nearest ones
        z = torch.tensor([5.0, math.inf, 1.0, 3.0, 2.0, 4.0, 6.0, 7.0][:m + 1] + [math.inf])[:, None]
        mask = metrics.near_third_mask(z)
        objects = z[torch.isfinite(z)]
        assert int(mask.sum()) == math.ceil(len(objects) / 3)
        assert float(z[mask].max()) <= float(objects.sort().values[math.ceil(len(objects) / 3) - 1])
    assert not metrics.near_third_mask(torch.full((3, 1), math.inf)).any()


def test_open_water_and_very_far_objects_give_finite_values():
    z = np.array([[1.0, math.inf, 1e3, 1e6, 1e300]])
    J = np.full((1, 5, 3), 0.5)
    I = ceiling.form_image(J, z, **WATER)
    assert np.all(np.isfinite(I)) and np.allclose(I[0, 1], WATER["B_inf"]) and np.allclose(I[0, 4], WATER["B_inf"])
    I_noisy = I + 1e-3  # the far pixels' signal is the noise: its inversion must still be finite
    J_hat, capped = ceiling.invert(I_noisy, z, **WATER)
    assert np.all(np.isfinite(J_hat)) and capped == 9  # 1e3 m and beyond: beta_D z > 690 in every channel
    assert np.array_equal(J_hat[0, 1], np.zeros(3))  # open water has no J
    assert np.allclose(J_hat[0, 0], J[0, 0] + 1e-3 * np.exp(WATER["beta_D"]))
    # clear air reaching to infinity: no 0 * inf
    assert np.array_equal(ceiling.backscatter_fraction(np.zeros(3), z), np.zeros((1, 5, 3)))
    J_hat, _ = ceiling.invert(I_noisy, z, np.zeros(3), np.zeros(3), np.zeros(3))
    assert np.all(np.isfinite(J_hat))
    fit = ceiling.fit_backscatter(I, J, z, WATER["beta_D"])  # open water left out of the fit
    assert fit.num_pixels == 4 and all(math.isfinite(v) for v in fit.beta_B + fit.B_inf + fit.rms)
    scores = metrics.clean_psnrs(torch.from_numpy(J_hat), torch.from_numpy(J), torch.from_numpy(z[..., None]))
    assert all(math.isfinite(v) for v in scores.values())
    with pytest.raises(ValueError, match="no object pixel"):
        ceiling.fit_backscatter(I[:, 1:2], J[:, 1:2], z[:, 1:2], WATER["beta_D"])


# ---------------------------------------------------------------- a scene


@pytest.fixture(scope="module")
def exact_scene(tmp_path_factory):
    """A tiny seathru-synth water scene with one ray per pixel: the model holds at every pixel."""
    from seathru_nerfstudio.data.synthetic import SynthConfig, generate

    folder = tmp_path_factory.mktemp("ceiling") / "water"
    generate(SynthConfig(output_dir=folder, preset="water", width=40, height=30, num_views=6, supersample=1))
    return folder


@pytest.fixture(scope="module")
def exact_ceiling(exact_scene):
    from seathru_nerfstudio.bench.ceiling_scene import scene_ceiling

    return scene_ceiling(exact_scene, "water")


def test_scene_ceiling_is_exact_up_to_the_16_bit_files(exact_scene, exact_ceiling):
    record = exact_ceiling
    assert record["held_out_views"] == ["frame_00000.png", "frame_00005.png"] and len(record["fit_views"]) == 4
    # I and J are rounded to 16 bits (uniform error, variance q^2/12 each): the fit's residual
    # I - J e^{-beta_D z} - backscatter is no larger than theirs together
    assert max(record["fit"]["rms"]) <= Q * math.sqrt(2 / 12)
    for key in ("beta_B", "B_inf"):  # within one 16-bit step relative to the smallest veil
        np.testing.assert_allclose(record["fit"][key], WATER[key], rtol=Q / min(WATER["B_inf"]))
    # per pixel |J^ - J| <= q/2 (e^{beta_D z} + 1): the PSNR that bound gives, per view
    bounds = []
    for name in record["held_out_views"]:
        z = np.load(exact_scene / "ground_truth" / "depth" / name.replace(".png", ".npy")).astype(np.float64)
        z = z[np.isfinite(z)]
        worst = (Q / 2 * (np.exp(np.outer(z, WATER["beta_D"])) + 1) + 1e-6) ** 2
        bounds.append(-10 * math.log10(worst.mean()))
    variant = record["variants"]["ceiling"]
    assert variant["capped_gains"] == 0
    assert variant["metrics"]["clean_psnr_objects"] >= sum(bounds) / len(bounds) > 60
    assert variant["metrics"]["clean_psnr_near_third"] >= variant["metrics"]["clean_psnr_objects"]
    full = record["variants"]["ceiling_all_fitted"]
    np.testing.assert_allclose(full["medium"]["beta_D"], WATER["beta_D"], rtol=Q / min(WATER["B_inf"]))
    assert record["reference"] == {"beta_D": list(WATER["beta_D"]), "beta_B": record["fit"]["beta_B"], "B_inf": record["fit"]["B_inf"]}


def test_ceiling_subcommand_prints_the_table_and_names_a_scene_without_truth(exact_scene, tmp_path, monkeypatch, capsys):
    from seathru_nerfstudio.bench.cli import entrypoint

    out = tmp_path / "ceiling.json"
    monkeypatch.setattr(sys, "argv", ["seathru-bench", "ceiling", "--scene", str(exact_scene), "--output", str(out)])
    entrypoint()
    printed = capsys.readouterr().out
    assert "| ceiling: true z, true β_D, fitted β_B, B∞ |" in printed and "| truth (medium.json) |" in printed
    record = json.loads(out.read_text())
    assert set(record["variants"]) == {"ceiling", "ceiling_all_fitted"}

    (tmp_path / "nogt").mkdir()
    (tmp_path / "nogt" / "transforms.json").write_text((exact_scene / "transforms.json").read_text())
    monkeypatch.setattr(sys, "argv", ["seathru-bench", "ceiling", "--scene", str(tmp_path / "nogt")])
    with pytest.raises(SystemExit) as stop:
        entrypoint()
    said = " ".join(capsys.readouterr().out.split())
    assert stop.value.code == 1 and "medium.json: no such file" in said


def test_report_puts_the_ceiling_beside_the_runs_and_compares_the_medium_with_its_fit(exact_ceiling, tmp_path):
    fit = exact_ceiling["fit"]

    def run(method, medium):
        record = {"step": 20, "train_time": 10.0, "metrics": {"psnr": 25.0, "clean_psnr_objects": 30.0, "clean_psnr_near_third": 40.0}}
        if medium:
            record["medium"] = {"beta_D": list(1.1 * WATER["beta_D"]), "beta_B": fit["beta_B"], "B_inf": list(0.5 * np.array(fit["B_inf"]))}
        return {"method": method, "scene": "water", "iterations": 20, "train_time": 10.0, "sec_per_iter": 0.5,
                "cpu_sec_per_iter": 0.4, "peak_rss_mb": 100.0, "evals": [record]}  # fmt: skip

    results = {"budget_kind": "iterations", "budget": 20, "machine": {}, "ceilings": {"water": exact_ceiling},
               "runs": [run("seathru-nerf-lite", True), run("nerfacto", False)]}  # fmt: skip
    scoring.reference_errors(results)
    error = results["runs"][0]["evals"][0]["medium_error_reference"]
    assert error["beta_D"]["rel_mean"] == pytest.approx(0.1) and error["beta_B"]["rel_mean"] == pytest.approx(0.0)
    assert error["B_inf"]["rel_mean"] == pytest.approx(0.5)
    table = report.write_report(results, tmp_path)["table"].read_text()
    lines = table.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("| water |"))
    assert "**ceiling: true z, true β_D, fitted β_B, B∞**" in lines[first] and "`seathru-nerf-lite`" in lines[first + 2]
    top = exact_ceiling["variants"]["ceiling"]["metrics"]
    assert f"{top['clean_psnr_objects']:.2f}" in lines[first] and f"{top['clean_psnr_near_third']:.2f}" in lines[first]
    assert "10% (10, 10, 10)" in lines[first + 2] and "50% (50, 50, 50)" in lines[first + 2]
    gap = f"{30.0 - top['clean_psnr_objects']:+.2f}"
    assert f"| water | `seathru-nerf-lite` | {gap} |" in table and "Gaps to the ceiling" in table


def test_the_scenes_registration_is_read_from_scene_json_and_said_in_one_line(exact_ceiling, tmp_path):
    """A path-traced scene's ``scene.json`` says how its poses were made; the benchmark says it
    beside the ceiling (a benchmark on wrong poses measures the SfM). A scene without that record
    (``seathru-synth``'s), or with an unreadable one, has none and gets no line."""
    from seathru_nerfstudio.bench.ceiling_scene import registration_line, scene_registration

    assert exact_ceiling["registration"] is None and registration_line(None) is None
    assert scene_registration(tmp_path) is None
    (tmp_path / "scene.json").write_text("{not json")
    assert scene_registration(tmp_path) is None
    sfm = {"poses": "sfm", "registered": 24, "total": 24, "rotation_error_deg_median": 5.2276, "alignment_residual_rms_m": 1.1588}
    (tmp_path / "scene.json").write_text(json.dumps({"registration": sfm}))
    assert scene_registration(tmp_path) == sfm
    line = registration_line(sfm)
    assert "24/24 views registered" in line and "5.23° median rotation error" in line and "1.159 m rms" in line
    assert registration_line({"poses": "truth", "registered": 24, "total": 24}) == "poses: truth (not structure from motion)"
    failed = registration_line({"poses": "sfm", "failed": "structure from motion registered 2 of 24 images"})
    assert failed == "poses: structure from motion failed (structure from motion registered 2 of 24 images)"
