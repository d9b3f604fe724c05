"""``seathru-medium``'s report, in units: per metre or per world unit, tied densities, the fit's
standard errors, the veil's rise, and a medium of the ray direction."""

from __future__ import annotations

import pytest
import torch

from tiny_training import make_scene, tiny_model


def test_medium_report_units_ties_fit_and_directions(tmp_path):
    """Unit: per metre is per scene unit times the dataparser scale; a tied model reports tied
    densities; the fit's standard errors; a medium of the ray direction gets its table."""
    from seathru_nerfstudio import medium_report

    model = tiny_model(metadata={"dataparser_scale": 4.0}, medium_model="uniform").eval()
    with torch.no_grad():
        model.medium_field.density_raw.copy_(torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5, 0.6]))
    report = medium_report.medium_report(model, medium_report.UNKNOWN_UNIT, 7)
    sigma = torch.nn.functional.softplus(torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], dtype=torch.float64))
    tied = (sigma[:3] + sigma[3:]) / 2 * 4.0  # uniform: one density per channel, scene units -> world units
    assert report["beta_D"] == pytest.approx(tied.tolist()) and report["beta_B"] == pytest.approx(tied.tolist())
    assert report["attenuation_length"] == pytest.approx((1 / tied).tolist())
    assert report["units"] == "1/world unit" and "unknown scale" in report["summary"]
    assert report["fit"] is None
    model.fit_log_error.copy_(torch.tensor([0.01, 0.02, 0.2], dtype=torch.float64))
    fit = medium_report.medium_report(model)["fit"]
    assert fit["standard_error_beta_D"] == pytest.approx((tied * torch.tensor([0.01, 0.02, 0.2])).tolist())
    assert "standard_error_ln_beta_B" not in fit  # -1: a checkpoint from before beta_B's were kept
    model.fit_backscatter_log_error.copy_(torch.tensor([0.3, 0.1, 0.05], dtype=torch.float64))
    model.backscatter_veil_sensitivity.copy_(torch.tensor([-5.5, -2.0, -2.9], dtype=torch.float64))
    report = medium_report.medium_report(model)
    assert report["fit"]["standard_error_ln_beta_B"] == pytest.approx([0.3, 0.1, 0.05])
    assert report["fit"]["ln_beta_B_per_ln_B_inf"] == pytest.approx([-5.5, -2.0, -2.9])
    assert "beta_B moves -5.5 -2 -2.9 times an error of B_inf" in report["summary"]

    assert "B_inf_rise" not in report  # no rise set
    water = tiny_model(medium_model="seathru").eval()
    water.medium_field.set_veil_rise(0.1, torch.tensor([0.0, 0.5, 2.0]), 0.3)
    rise = medium_report.medium_report(water)
    down = torch.tensor(rise["B_inf"], dtype=torch.float64)
    assert rise["B_inf_rise"]["above_sin_elevation"] == pytest.approx([0.1, 0.1, 0.1])
    assert rise["B_inf_rise"]["up_to_sin_elevation"] == pytest.approx(0.3)
    expected = (down * (1 + torch.tensor([0.0, 0.5, 2.0], dtype=torch.float64) * (0.3 - 0.1))).clamp(max=1.0)
    assert rise["B_inf_rise"]["B_inf_highest"] == pytest.approx(expected.tolist(), rel=1e-5)
    assert rise["B_inf_rise"]["vertical"] == pytest.approx([0.0, 0.0, 1.0])
    water.medium_field.set_vertical([0.0, 0.6, 0.8])  # elevations along a tilted up: the same veil at its top
    tilted = medium_report.medium_report(water)["B_inf_rise"]
    assert tilted["vertical"] == pytest.approx([0.0, 0.6, 0.8]) and tilted["B_inf_highest"] == pytest.approx(expected.tolist(), rel=1e-5)
    assert "B_inf looking up to" in rise["summary"]
    assert "B_inf_across" not in rise  # no change round the horizon set
    level = torch.tensor(rise["B_inf"])
    water.medium_field.set_vertical([0.0, 0.0, 1.0])
    change = torch.tensor([[0.4, 0.0, -0.2], [0.1, 0.2, 0.3]])
    water.medium_field.set_veil_across(torch.tensor([0.2, 0.9]), change, torch.tensor([-0.5, 0.7]), torch.tensor([0.5, 1.0]))
    across = medium_report.medium_report(water)
    assert across["B_inf"] == pytest.approx(level.tolist(), rel=1e-5)  # at the mean heading: the factor is 1
    torch.testing.assert_close(torch.tensor(across["B_inf_across"]["change"], dtype=torch.float64), change.double())
    torch.testing.assert_close(torch.tensor(across["B_inf_across"]["level_axes"], dtype=torch.float64), torch.eye(3)[:2].double())
    assert (across["B_inf_across"]["mean"], across["B_inf_across"]["low"]) == (pytest.approx([0.2, 0.9]), pytest.approx([-0.5, 0.7]))

    assert "B_inf_open_water" not in across  # one veil
    water.medium_field.surface_veil.copy_(torch.tensor([0.8, 0.9, 1.0]))  # the surfaces' veil below the open water's
    two = medium_report.medium_report(water)
    assert two["B_inf_open_water"] == pytest.approx(level.tolist(), rel=1e-5)
    assert two["B_inf"] == pytest.approx((level * torch.tensor([0.8, 0.9, 1.0])).tolist(), rel=1e-5)

    ray = tiny_model(medium_model="seathru", medium_scope="ray").eval()
    report = medium_report.medium_report(ray, view_directions=torch.tensor([[0.0, 0.0, -1.0]]))
    grid = medium_report.direction_grid()
    assert len(report["directions"]) == len(grid) and torch.allclose(grid.norm(dim=-1), torch.ones(len(grid)))
    tilted_up = torch.tensor([0.0, 0.6, 0.8])
    tilted_grid = medium_report.direction_grid(tilted_up)  # the same table about another up: elevations along it
    assert torch.allclose(tilted_grid @ tilted_up, grid[:, 2], atol=1e-6)
    assert torch.allclose(tilted_grid @ tilted_grid.T, grid @ grid.T, atol=1e-6)  # the same angles between rows
    with torch.no_grad():
        one = ray.medium(torch.tensor([[0.0, 0.0, -1.0]]))
    assert report["beta_D"] == pytest.approx(one.sigma_attn[0].tolist(), rel=1e-5)
    row = report["directions"][3]
    with torch.no_grad():
        there = ray.medium(torch.tensor([row["direction"]]))
    assert row["beta_B"] == pytest.approx(there.sigma_bs[0].tolist(), rel=1e-5)

    synth = make_scene(tmp_path)
    assert medium_report.world_unit(synth) == medium_report.METRE
    (tmp_path / "colmap").mkdir()
    (tmp_path / "colmap" / "transforms.json").write_text("{}")
    assert medium_report.world_unit(tmp_path / "colmap") == medium_report.UNKNOWN_UNIT
