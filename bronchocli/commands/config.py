"""`bronchopose config`: show the resolved configuration and the grid it expands to."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from ..cells import FIELDS
from ..config import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt, console, load


def config(
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
    grid: bool = typer.Option(False, "--grid", help="List the plan's cells (per stage) instead of the YAML."),
) -> None:
    """Validate experiments.yaml (with --profile and --set applied) and print it resolved, or its cells.

    Exits with code 2 and one message listing every problem when the config is invalid.
    """
    cfg = load(config, profile, set_)
    if not grid:
        console.print(cfg.to_yaml(), end="", markup=False, highlight=False)
        return
    from ..sweep.plan import plan_stages  # lazy: keeps `bronchopose --help` fast

    total = 0
    for sp in plan_stages(cfg, None):  # a procedural dataset's patients are known before it exists
        title = f"{cfg.name}" + ("" if sp.stage.name == "grid" else f", stage {sp.stage.name}")
        if sp.cells is None:
            console.print(f"{title}: the top {sp.stage.select.top} combinations of stage "
                          f"{sp.stage.source or 'before'} by {sp.stage.select.by}, chosen when it is done")
            continue
        table = Table("key", *FIELDS, title=title)
        for c in sp.cells:
            table.add_row(c.key, *(v or "-" for v in c.tags().values()))
        console.print(table)
        total += len(sp.cells)
    console.print(f"{total} cells")
