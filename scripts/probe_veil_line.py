"""The veil the first stage read, against the scene's best-fit veil, from a saved run (no training, seconds).

For each ``seathru-bench`` output folder run with ``--save-model`` on a scene with ground truth, reads the last
checkpoint's ``open_water_colour`` sums (``medium_start.OpenWaterColour``: the open rays of the first stage's second
half) and prints, per channel, as a ratio to the best-fit ``B_inf`` of the scene's ``ground_truth/medium.json``:

* the mean colour of the open rays above the level plane (``sin(elevation) > 0``), and their mean elevation;
* the level of their least-squares line over ``sin(elevation)``, ``colour_mean - slope * up_mean``: the open water
  seen at the level ray, read from the rays that look up (history.md, 2026-12-03 (after 51f8982)).

The held veil itself is the run's ``B_inf`` in its ``results.json`` (``medium`` of any evaluation after step 200).

    .venv/bin/python scripts/probe_veil_line.py outputs/bench/fog_s4_42 outputs/bench/coastal_s5_42
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from seathru_nerfstudio.medium_start import OpenWaterColour

SUMS_KEY = "_model.open_water_colour._extra_state"


def ratios(values: torch.Tensor, reference: torch.Tensor) -> str:
    return ", ".join(f"{float(v):.3f}" for v in values / reference)


def main(folders: list[str]) -> None:
    for folder in map(Path, folders):
        checkpoints = sorted(folder.glob("runs/*/seathru-nerf-lite/run/*/*/nerfstudio_models/step-*.ckpt"))
        if not checkpoints:
            print(f"{folder}: no seathru-nerf-lite checkpoint (run seathru-bench with --save-model)")
            continue
        sums = OpenWaterColour()
        sums.set_extra_state(torch.load(checkpoints[-1], map_location="cpu", weights_only=False)["pipeline"][SUMS_KEY])
        scene = Path(json.loads((folder / "results.json").read_text())["runs"][0]["scene_path"])
        truth = scene / "ground_truth" / "medium.json"
        if not truth.is_file():
            print(f"{truth}: missing (a scene with ground truth is needed)")
            continue
        best_fit = torch.tensor(json.loads(truth.read_text())["B_inf"], dtype=torch.float64)
        line = sums.line_above_level()
        if line is None:
            print(f"{folder}: too few open rays above the level for a line")
            continue
        up, colour, slope = line
        count = float(sums.above_level[0])
        print(f"{folder} ({checkpoints[-1].name}): {count:.0f} open rays above the level, mean sin(elevation) {up:.3f}")
        print(f"  their mean colour / best-fit B_inf:    {ratios(colour, best_fit)}")
        print(f"  their line at the level / best-fit B_inf: {ratios(colour - slope * up, best_fit)}")


if __name__ == "__main__":
    main(sys.argv[1:])
