"""`bronchopose config`: show the resolved configuration and the grid it expands to."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

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
    patients = None
    if cfg.grid.folds == "all" and "cross-subject" in cfg.grid.population:
        # Patient ids of a procedural dataset are known before it exists.
        from ..data.naming import patient_ids_for  # noqa: PLC0415 (keeps start-up light)

        patients = patient_ids_for(cfg)
    table = Table("key", "arch", "rot_loss", "population", "fold", "seed", "pose_frame", title=f"grid of {cfg.name}")
    cells = expand_grid(cfg, patients)
    for c in cells:
        table.add_row(c.key, c.arch, c.rot_loss, c.population, c.fold or "-", str(c.seed), c.pose_frame)
    console.print(table)
    console.print(f"{len(cells)} cells")
