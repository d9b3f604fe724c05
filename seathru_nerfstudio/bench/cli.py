"""``seathru-bench``: ``run`` (methods x scenes), ``numerics`` (renderer quadratures),
``report`` (table and plots again from a results.json)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Union

import tyro
from typing_extensions import Annotated

from seathru_nerfstudio.bench.runner import RunConfig


@dataclass
class ReportConfig:
    """Write results.md and the plots again from an existing results.json."""

    results: Path = Path("outputs/bench/results.json")
    """The results.json of a `seathru-bench run`."""


def entrypoint() -> None:
    from seathru_nerfstudio.bench.numerics import NumericsConfig

    command = tyro.cli(
        Union[
            Annotated[RunConfig, tyro.conf.subcommand("run", default=RunConfig())],
            Annotated[NumericsConfig, tyro.conf.subcommand("numerics", default=NumericsConfig())],
            Annotated[ReportConfig, tyro.conf.subcommand("report", default=ReportConfig())],
        ]
    )
    if isinstance(command, RunConfig):
        from seathru_nerfstudio.bench.runner import run_benchmark

        run_benchmark(command)
    elif isinstance(command, NumericsConfig):
        from seathru_nerfstudio.bench.numerics import run_numerics

        run_numerics(command)
    else:
        import json

        from seathru_nerfstudio.bench.report import write_report

        write_report(json.loads(command.results.read_text()), command.results.parent)


if __name__ == "__main__":
    entrypoint()
