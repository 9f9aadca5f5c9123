"""The plan as the sweep's commands print it: per stage its cells and their state (``sweep plan``, and ``sweep
run`` before it submits), what a stage waits for, the outcome of a stage and the workers that ended without a
cell's row saying why. Nothing here starts or stops anything (the driver is ``launch``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from ..cells import Selection
from ..config import Config, Stage
from ..generation import check_dataset
from . import plan as planning
from . import record
from .plan import cells_left
from .selection import describe_selection
from .status import failures, plan_table, progress, row_lines, summary_line
from .storage import FINISHED, SweepStore
from .worker import EXIT_INTERRUPTED, EXIT_RECORDED

log = logging.getLogger(__name__)


def workers_for(plan: planning.Plan, max_retries: int, workers: int) -> int:
    """The local workers a run of ``plan`` starts: a worker per cell left at most (more would only wait)."""
    return min(workers, cells_left(plan, max_retries))


def print_plan(console: Console, plan: planning.Plan, cfg: Config, workers: int | None, title: str,
               store: SweepStore) -> None:
    """The plan's table, its counts and the workers a run starts here; a line per claims row that is not as this
    code writes it (damaged, a heartbeat from the future, a foreign worker id: ``status.row_lines``)."""
    max_retries = cfg.sweep.max_retries
    console.print(plan_table(plan, max_retries, title))
    c = plan.counts()
    console.print(f"{len(plan.cells)} cells: {c['finished']} finished, {c['running']} running, {c['failed']} failed, "
                  f"{c['pending']} pending" + (f", {c['damaged']} damaged (set aside)" if c["damaged"] else "")
                  + (f"; workers here: {workers_for(plan, max_retries, workers)}" if workers is not None else ""))
    now = store.db_now() if store.exists() else None
    for line in row_lines(plan, (), store.redacted, now, cfg.sweep.stale_after_s):
        console.print(line, highlight=False, soft_wrap=True)


def stage_title(stage: Stage, n_stages: int) -> str:
    if n_stages == 1 and stage.name == "grid":
        return ""
    how = f"top {stage.select.top} of {stage.source or 'the previous stage'} by {stage.select.by}" \
        if stage.select else "grid"
    return f"stage {stage.name} ({how})"


def dry_run(cfg: Config, store: SweepStore, only: Selection, workers: int, console: Console) -> None:
    check_dataset(cfg)  # what `train` refuses, the plan refuses too (a dataset not generated yet passes)
    record.check_experiment(cfg)  # deleted by hand: the line `sweep run`, `status` and `report` give
    stages = planning.StageWalk(cfg, store, only).plans()
    for sp in stages:
        if sp.cells is None:
            console.print(f"[bold]{stage_title(sp.stage, len(stages))}[/]: cells known once stage "
                          f"{planning.source_of(cfg, sp.stage).name} is done")
            continue
        if sp.selection is not None:
            console.print(describe_selection(sp.selection), highlight=False)
        plan = planning.read_plan(store, cfg.name, sp.cells)
        rows, known = record.overlay(cfg, plan.sweep, plan.cells, plan.rows)
        print_plan(console, planning.Plan(plan.sweep, plan.cells, rows), cfg, workers,
                   stage_title(sp.stage, len(stages)), store)
        if known:
            console.print(f"{known} cell(s) FINISHED in MLflow but not in the claims table: shown finished, never "
                          "trained again (a sweep records them there)", highlight=False)
    console.print("[dim]dry run: nothing started[/]")


def report_workers(console: Console, codes: Sequence[int | None], log_dir: Path) -> None:
    """The workers that ended without a cell's row saying why. Not crashes: 0, 130 (stopped) and ``EXIT_RECORDED``
    (stopped after a full disk failed its cell: that cell's failure line says so); 2 is a user error, its one line
    in the worker's log; anything else (a traceback, a signal) crashed."""
    errors = [c for c in codes if c == 2]
    crashed = [c for c in codes if c not in (0, 2, EXIT_INTERRUPTED, EXIT_RECORDED)]
    if errors:
        console.print(f"[red]{len(errors)} worker(s) stopped on an error[/] (exit code 2; the error is the last line of "
                      f"each one's log in {log_dir})", highlight=False)
        for line in error_lines(log_dir):
            console.print(f"  {line}", highlight=False, markup=False)
    if crashed:
        console.print(f"[red]{len(crashed)} worker(s) crashed[/] (exit codes {crashed}); logs in {log_dir}",
                      highlight=False)


def error_lines(log_dir: Path) -> list[str]:
    """The error each of this process's local workers ended on: the last line of its log (named
    ``<host>-<this pid>-w<n>.log`` by ``launchers.local``) when it is an ERROR line, without its time and worker."""
    out = []
    for path in sorted(log_dir.glob(f"*-{os.getpid()}-w*.log")):
        try:
            lines = path.read_text(errors="replace").rstrip().splitlines()
        except OSError:
            continue
        if lines and " ERROR " in lines[-1]:
            out.append(lines[-1].split(" ERROR ", 1)[1].split(": ", 1)[-1])
    return out


def waits_line(step: planning.Step) -> str:
    """A stage that cannot start: cells of its source stage are not done (excluded by ``--only``, or elsewhere)."""
    return (f"[yellow]stage {step.stage.name} waits:[/] {step.waits} cell(s) of stage {step.source.name} are not "
            "done (excluded by --only, or running elsewhere); run the sweep again later")


def final(console: Console, plan: planning.Plan, max_retries: int) -> int:
    """The summary line and each failed cell's reason; 0 when every cell of ``plan`` finished, else 1."""
    console.print(summary_line(progress(plan, max_retries, 1)))
    for label, reason in failures(plan):
        console.print(f"[red]failed[/] {label}: {reason}", highlight=False)
    states = [plan.state(c) for c in plan.cells]
    return 0 if all(s == FINISHED for s in states) else 1
