"""`bronchopose config`: show the resolved configuration and the grid it expands to."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from ..cells import FIELDS
from ..config import DEFAULT_CONFIG, expand_grid
from .common import ConfigOpt, ProfileOpt, SetOpt, console, load


def config(
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
    grid: bool = typer.Option(False, "--grid", help="List the grid cells instead of the resolved YAML."),
) -> None:
    """Validate experiments.yaml (with --profile and --set applied) and print it resolved, or its grid.

    Exits with code 2 and one message listing every problem when the config is invalid.
    """
    cfg = load(config, profile, set_)
    if not grid:
        console.print(cfg.to_yaml(), end="", markup=False, highlight=False)
        return
    from ..generation.sources import planned_patients  # lazy: keeps `bronchopose --help` fast

    table = Table("key", *FIELDS, title=f"grid of {cfg.name}")
    grid_cells = expand_grid(cfg, planned_patients(cfg))  # a procedural dataset's patients are known beforehand
    for c in grid_cells:
        table.add_row(c.key, *(v or "-" for v in c.tags().values()))
    console.print(table)
    console.print(f"{len(grid_cells)} cells")
