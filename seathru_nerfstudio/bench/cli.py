"""``seathru-bench``: ``run`` (methods x scenes), ``numerics`` (renderer quadratures),
``report`` (table and plots again from a results.json), ``render-cost`` (a camera render's
cost by the outputs read), ``ceiling`` (a scene's ceiling, without training)."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple, Union

import tyro
from typing_extensions import Annotated

from nerfstudio.utils.rich_utils import CONSOLE
from seathru_nerfstudio.bench.runner import RunConfig
from seathru_nerfstudio.data.io import write_text_atomic
from seathru_nerfstudio.quiet import silence_upstream_warnings


@dataclass
class ReportConfig:
    """Write results.md and the plots again from results.json files (several are merged:
    their runs are concatenated, the machine record is the first file's)."""

    results: Tuple[Path, ...] = (Path("outputs/bench/results.json"),)
    """results.json files of `seathru-bench run`."""
    output_dir: Optional[Path] = None
    """Where to write (default: beside the first results.json); with several inputs, the
    merged results.json is written there too."""


@dataclass
class CeilingConfig:
    """Print the ceiling of a scene with ground truth, without training (seconds): the formation
    model inverted with the true range and the best-fitting medium, scored on the held-out views."""

    scene: Path
    """A scene folder with transforms.json whose frames declare gt_clean_file_path and
    gt_depth_file_path, and ground_truth/medium.json (seathru-synth writes both)."""
    output: Optional[Path] = None
    """Also write the ceiling record (JSON) to this file."""


def run_ceiling(config: CeilingConfig) -> None:
    import json

    from seathru_nerfstudio.bench.ceiling_scene import registration_line, scene_ceiling
    from seathru_nerfstudio.bench.report import ceiling_table

    if not (config.scene / "transforms.json").is_file():
        raise ValueError(f"{config.scene}: no transforms.json (not a nerfstudio scene folder)")
    record = scene_ceiling(config.scene)
    print(ceiling_table(record), end="")
    poses = registration_line(record["registration"])
    if poses is not None:
        print(poses)
    if config.output is not None:
        write_text_atomic(config.output, json.dumps(record, indent=1, default=float))
        CONSOLE.print(f"seathru-bench: wrote {config.output}")


def entrypoint() -> None:
    from seathru_nerfstudio.bench.numerics import NumericsConfig
    from seathru_nerfstudio.bench.render_cost import RenderCostConfig

    silence_upstream_warnings()
    command = tyro.cli(
        Union[
            Annotated[RunConfig, tyro.conf.subcommand("run", default=RunConfig())],
            Annotated[NumericsConfig, tyro.conf.subcommand("numerics", default=NumericsConfig())],
            Annotated[ReportConfig, tyro.conf.subcommand("report", default=ReportConfig())],
            Annotated[RenderCostConfig, tyro.conf.subcommand("render-cost", default=RenderCostConfig())],
            Annotated[CeilingConfig, tyro.conf.subcommand("ceiling")],
        ]
    )
    if isinstance(command, CeilingConfig):
        try:
            run_ceiling(command)
        except ValueError as error:  # no or unreadable ground truth: one line naming the file
            CONSOLE.print(f"[bold red]Error: seathru-bench ceiling: {error}", markup=True, highlight=False)
            sys.exit(1)
        return
    if isinstance(command, RunConfig):
        from seathru_nerfstudio.bench.methods import MethodSpecError
        from seathru_nerfstudio.bench.runner import run_benchmark

        try:
            run_benchmark(command)
        except MethodSpecError as error:
            CONSOLE.print(f"[bold red]Error: seathru-bench: {error}")
            sys.exit(1)
    elif isinstance(command, RenderCostConfig):
        from seathru_nerfstudio.bench.render_cost import run_render_cost

        run_render_cost(command)
    elif isinstance(command, NumericsConfig):
        from seathru_nerfstudio.bench.numerics import run_numerics

        run_numerics(command)
    else:
        import json

        from seathru_nerfstudio.bench.report import merge_results, write_report

        results = merge_results([json.loads(p.read_text()) for p in command.results])
        out = command.output_dir or command.results[0].parent
        if len(command.results) > 1:
            out.mkdir(parents=True, exist_ok=True)
            write_text_atomic(out / "results.json", json.dumps(results, indent=1, default=float))
        write_report(results, out)


if __name__ == "__main__":
    entrypoint()
