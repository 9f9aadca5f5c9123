"""`bronchopose config`: show the resolved configuration and the grid it expands to."""

from __future__ import annotations

from pathlib import Path

import typer

from ..api.arguments import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt, console


def config(
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
    grid: bool = typer.Option(False, "--grid", help="List the plan's cells (per stage) instead of the YAML."),
) -> None:
    """Validate experiments.yaml (with --profile and --set applied) and print it resolved, or its cells.

    Exits with code 2 and one message listing every problem when the config is invalid, or one line when a
    path it names could not be written: the same checks `sweep` makes before it starts (creates nothing, contacts
    no server).
    """
    from ..api import manage  # lazy: keeps `bronchopose --help` fast

    cfg = manage.check_config(config, profile, set_ or ())  # what `sweep` checks: launchers, paths, ...
    if not grid:
        console.print(cfg.to_yaml(), end="", markup=False, highlight=False)
        return
    manage.grid(cfg, console)
