"""`bronchopose config`: show the resolved configuration and the grid it expands to."""

from __future__ import annotations

from pathlib import Path

import typer

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
    from ..sweep import entry  # lazy: keeps `bronchopose --help` fast

    entry.grid(cfg, console)
