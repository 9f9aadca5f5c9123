"""`bronchopose config`: show the resolved configuration and the grid it expands to."""

from __future__ import annotations

from pathlib import Path

import typer

from ..config import DEFAULT_CONFIG, check_paths
from .common import ConfigOpt, ProfileOpt, SetOpt, console, load


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
    cfg = load(config, profile, set_)
    from ..sweep.launchers import log_roots  # lazy: keeps `bronchopose --help` fast

    # sweep.launcher a known launcher, each sweep.launchers section valid (the config package cannot see them)
    roots = log_roots(cfg)
    check_paths(cfg, storage=True, logs=True, extra=roots)  # what `sweep` checks: roots inside each other, ...
    if not grid:
        console.print(cfg.to_yaml(), end="", markup=False, highlight=False)
        return
    from ..sweep import entry  # lazy: keeps `bronchopose --help` fast

    entry.grid(cfg, console)
