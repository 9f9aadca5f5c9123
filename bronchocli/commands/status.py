"""`bronchopose status`: per-cell state of a sweep, its MLflow runs and headline metrics."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .. import cells
from ..config import DEFAULT_CONFIG
from ..errors import BronchoError
from .common import ConfigOpt, ProfileOpt, SetOpt, load
from .common import console as _console


def status(
    sweep: Optional[str] = typer.Option(None, "--sweep", help="Sweep name (default: the config's name)."),
    show_all: bool = typer.Option(False, "--all",
                                  help="Every stored cell of the sweep, also those of earlier configs."),
    storage: Optional[str] = typer.Option(None, "--storage", help="Claims database URL, overriding storage.url."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Show each cell of a sweep: state, attempts, MLflow run id, duration, pair and accumulated position L2.

    Cells are those of the config's grid (a changed config means new cells); `--all`
    or another `--sweep` name lists every stored cell instead. Failed cells are listed
    with their reason.
    """
    from ..sweep import SweepStore, plan_cells, read_plan  # lazy: keeps `bronchopose --help` fast
    from ..sweep.status import failures, fetch_metrics, progress, status_table, summary_line, wide

    console = wide(_console)
    cfg = load(config, profile, set_)
    if storage:
        cfg = cfg.with_values({"storage.url": storage})
    store = SweepStore(cfg.paths.storage_url)
    name = sweep or cfg.name
    if not store.exists():
        console.print(f"no sweep has used storage {store.redacted} yet")
        if sweep:
            return
    if show_all or name != cfg.name:
        plan = _stored_plan(store, name)
    else:
        plan = read_plan(store, name, plan_cells(cfg))
        stale = len(store.rows(name)) - len(plan.rows) if store.exists() else 0
        if stale > 0:
            console.print(f"[dim]{stale} stored cell(s) of sweep {name} belong to another version of the config "
                          f"(--all shows them)[/]")
    finished = [plan.rows[c.key].run_id for c in plan.cells if c.key in plan.rows and plan.rows[c.key].run_id]
    console.print(status_table(plan, fetch_metrics(cfg, finished), cfg.sweep.max_retries))
    console.print(summary_line(progress(plan, cfg.sweep.max_retries, 1)))
    for label, reason in failures(plan):
        console.print(f"[red]failed[/] {label}: {reason}", highlight=False)


def _stored_plan(store, name: str):
    from ..sweep.plan import Plan  # lazy: keeps `bronchopose --help` fast

    rows = store.rows(name) if store.exists() else []
    if not rows:
        known = ", ".join(store.sweeps()) if store.exists() else ""
        raise BronchoError(f"--sweep {name}: no such sweep in storage {store.redacted} (stored: {known or 'none'})")
    stored = [cells.make(**r.coords, key=r.cell_key) for r in rows]
    return Plan(name, stored, {r.cell_key: r for r in rows})
