"""``bronchopose sweep run`` with the local launcher: the plan's stages in order, each with the local worker pool.

Every stage's cells are claimed exactly once across all processes and machines
(the claims table); a stage that selects from an earlier one waits until all
of that stage's cells are done (FINISHED, or FAILED with no retry left), then
settles its selection and runs the chosen cells (both decided by the one stage
walk, ``plan.StageWalk``). Cells already FINISHED (in any stage) are never run
again. Each worker walks the same stages up to the one it was started for (``stagework.work_stages``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from .. import urls
from ..cells import Selection
from ..config import Config, Stage
from ..generation import check_dataset
from ..runs.client import client_for, experiment_id
from ..runs.parents import set_parent_status, start_parent, sweep_parent
from . import plan as planning
from . import record
from .plan import cells_left
from .pool import EXIT_INTERRUPTED, run_pool
from .selection import describe_selection
from .status import failures, plan_table, progress, row_lines, summary_line
from .storage import FINISHED, SweepStore
from .summary import record_parent, uncancel
from .worker import EXIT_RECORDED, Runner, default_runner

log = logging.getLogger(__name__)


def workers_for(plan: planning.Plan, max_retries: int, workers: int) -> int:
    """The local workers a run of ``plan`` starts: a worker per cell left at most (more would only wait)."""
    return min(workers, cells_left(plan, max_retries))


def _print_plan(console: Console, plan: planning.Plan, cfg: Config, workers: int, title: str,
                store: SweepStore) -> None:
    """The plan's table, its counts and the workers a run starts here; a line per claims row that is not as this
    code writes it (damaged, a heartbeat from the future, a foreign worker id: ``status.row_lines``)."""
    max_retries = cfg.sweep.max_retries
    console.print(plan_table(plan, max_retries, title))
    c = plan.counts()
    console.print(f"{len(plan.cells)} cells: {c['finished']} finished, {c['running']} running, {c['failed']} failed, "
                  f"{c['pending']} pending" + (f", {c['damaged']} damaged (set aside)" if c["damaged"] else "")
                  + f"; workers here: {workers_for(plan, max_retries, workers)}")
    now = store.db_now() if store.exists() else None
    for line in row_lines(plan, (), store.redacted, now, cfg.sweep.stale_after_s):
        console.print(line, highlight=False, soft_wrap=True)


def _stage_title(stage: Stage, n_stages: int) -> str:
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
            console.print(f"[bold]{_stage_title(sp.stage, len(stages))}[/]: cells known once stage "
                          f"{planning.source_of(cfg, sp.stage).name} is done")
            continue
        if sp.selection is not None:
            console.print(describe_selection(sp.selection), highlight=False)
        plan = planning.read_plan(store, cfg.name, sp.cells)
        rows, known = record.overlay(cfg, plan.sweep, plan.cells, plan.rows)
        _print_plan(console, planning.Plan(plan.sweep, plan.cells, rows), cfg, workers,
                    _stage_title(sp.stage, len(stages)), store)
        if known:
            console.print(f"{known} cell(s) FINISHED in MLflow but not in the claims table: shown finished, never "
                          "trained again (a sweep records them there)", highlight=False)
    console.print("[dim]dry run: nothing started[/]")


def run_sweep(cfg: Config, store: SweepStore, *, only: Selection, workers: int, console: Console,
              retry_failed: bool = False, gpus: Sequence[str] = (), runner: Runner = default_runner) -> int:
    """Run every stage; exit code 0 (all FINISHED), 1 (some FAILED), 130 (interrupted).

    The sweep's parent MLflow run (its cells nest under it) is RUNNING while this runs and ends like it, with
    the plan, its selections and its outcome recorded (``summary.record_parent``).
    """
    console.print(f"[bold]sweep[/] {cfg.name}  storage {store.redacted}  MLflow {urls.redact(cfg.paths.mlflow_uri)}"
                  f"  experiment {cfg.experiment_name}" + (f"  hyperparameters {cfg.tune.applied}"
                                                           if cfg.tune.applied else "")
                  + (f"  GPUs {','.join(gpus)} ({workers} workers)" if gpus else ""))
    walk, _ = planning.prepare_walk(cfg, store, only, retry_failed=retry_failed)
    client = client_for(cfg)
    parent = sweep_parent(client, cfg, experiment_id(client, cfg))
    start_parent(client, parent)  # RUNNING, with this process: `status --repair` ends it if we are killed
    uncancel(client, parent)  # an explicit run: a `sweep cancel` before it no longer holds
    code = 1
    try:
        record_parent(client, parent, walk)  # the plan; the outcome when the sweep ends (finally)
        code = _run_stages(walk, workers=workers, console=console, gpus=gpus, runner=runner, only=only)
        return code
    except KeyboardInterrupt:
        code = EXIT_INTERRUPTED
        raise
    finally:
        record_parent(client, parent, walk, finished=True)
        set_parent_status(client, parent, code)


def _run_stages(walk: planning.StageWalk, *, workers: int, console: Console, gpus: Sequence[str],
                runner: Runner, only: Selection) -> int:
    cfg, store = walk.cfg, walk.store
    code, ran_any = 0, False
    for step in walk.steps():
        if step.waits:
            console.print(f"[yellow]stage {step.stage.name} waits:[/] {step.waits} cell(s) of stage "
                          f"{step.source.name} are not done (excluded by --only, or running elsewhere); run the "
                          "sweep again later")
            break
        if step.settled is not None:
            console.print(describe_selection(step.settled), highlight=False)
        if not step.cells:
            continue
        plan = planning.ensure_rows(cfg, store, step.cells)  # prepared once; a stage settled now: added here
        left = cells_left(plan, cfg.sweep.max_retries)
        n_workers = workers_for(plan, cfg.sweep.max_retries, workers)
        _print_plan(console, plan, cfg, workers, _stage_title(step.stage, len(walk.stages)), store)
        if left:
            ran_any = True
            result = run_pool(cfg, store, plan, workers=n_workers, runner=runner, console=console, gpus=gpus,
                              only=only, stage=step.stage.name)
            if result.interrupted:
                console.print("[yellow]interrupted:[/] running cells were released; run the same command again "
                              "to resume")
                return EXIT_INTERRUPTED
            report_workers(console, result.worker_codes, result.log_dir)
            plan = result.plan
        code = max(code, _final(console, plan, cfg.sweep.max_retries))
    if not ran_any:
        console.print("nothing left to run")
    return code


def report_workers(console: Console, codes: Sequence[int | None], log_dir: Path) -> None:
    """The workers that ended without a cell's row saying why. Not crashes: 0, 130 (stopped) and ``EXIT_RECORDED``
    (stopped after a full disk failed its cell: that cell's failure line says so); 2 is a user error, its one line
    in the worker's log; anything else (a traceback, a signal) crashed."""
    errors = [c for c in codes if c == 2]
    crashed = [c for c in codes if c not in (0, 2, EXIT_INTERRUPTED, EXIT_RECORDED)]
    if errors:
        console.print(f"[red]{len(errors)} worker(s) stopped on an error[/] (exit code 2; the error is the last line of "
                      f"each one's log in {log_dir})", highlight=False)
    if crashed:
        console.print(f"[red]{len(crashed)} worker(s) crashed[/] (exit codes {crashed}); logs in {log_dir}",
                      highlight=False)


def _final(console: Console, plan: planning.Plan, max_retries: int) -> int:
    console.print(summary_line(progress(plan, max_retries, 1)))
    for label, reason in failures(plan):
        console.print(f"[red]failed[/] {label}: {reason}", highlight=False)
    states = [plan.state(c) for c in plan.cells]
    return 0 if all(s == FINISHED for s in states) else 1
