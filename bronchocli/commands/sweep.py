"""`bronchopose sweep`: run every cell of the grid exactly once with local workers over shared storage."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .. import urls
from ..cells import FIELDS, parse_only
from ..config import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt, load
from .common import console as _console

ONLY_HELP = ("Run only matching cells: key=value[,value...], keys joined by ';' or repeated --only "
             f"({', '.join(FIELDS)}), e.g. --only 'arch=lstm,conv3d;population=personalized'.")
STORAGE_HELP = ("Claims database URL, overriding storage.url (sqlite:///runs/sweep.db; "
                "postgresql://user:${PGPASSWORD}@host/db for many machines).")


def sweep(
    workers: int = typer.Option(1, "--workers", "-w", min=1,
                                help="Local worker processes (torch threads = cores / N)."),
    storage: Optional[str] = typer.Option(None, "--storage", help=STORAGE_HELP),
    only: Optional[list[str]] = typer.Option(None, "--only", help=ONLY_HELP),
    dry_run: bool = typer.Option(False, "--dry-run", help="Print the plan (cells and their state) and exit."),
    retry_failed: bool = typer.Option(False, "--retry-failed",
                                      help="Reset FAILED cells (and their retry budget) first."),
    use_tuned: Optional[str] = typer.Option(None, "--use-tuned",
                                            help="Apply the best trial of this Optuna study to every cell."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Run the grid of the config (arch x rot_loss x population x folds x seed x pose_frame), each cell once.

    Prints the plan, generates the dataset if missing, then runs every cell that is
    not FINISHED with N local worker processes and shows live progress. Any number of
    `bronchopose sweep` processes, on any machines, pointed at the same storage
    cooperate: each cell is claimed by one worker and yields one FINISHED MLflow run.
    Re-running resumes (FINISHED cells are skipped); FAILED cells are retried up to
    sweep.max_retries; a killed worker's cell is taken over after sweep.stale_after_s.
    Exit code 0 when every cell finished, 1 when some failed, 130 when interrupted.
    """
    from .. import sweep as sw  # lazy: keeps `bronchopose --help` fast
    from ..sweep.pool import cells_left
    from ..sweep.status import wide

    console = wide(_console)
    cfg = load(config, profile, set_)
    selection = parse_only(only)
    if storage:
        cfg = cfg.with_values({"storage.url": storage})
    if use_tuned:  # new values -> new cell keys: tuned cells never reuse untuned runs
        from ..sweep.tuning import apply_best  # lazy: optuna only with --use-tuned

        cfg = apply_best(cfg, use_tuned)
    store = sw.SweepStore(cfg.paths.storage_url)
    console.print(f"[bold]sweep[/] {cfg.name}  storage {store.redacted}  MLflow {urls.redact(cfg.paths.tracking_uri)}"
                  f"  experiment {cfg.experiment_name}" + (f"  hyperparameters {cfg.tune.applied}" if use_tuned else ""))
    if dry_run:
        plan = sw.read_plan(store, cfg.name, sw.plan_cells(cfg, selection))
        _print_plan(console, plan, cfg.sweep.max_retries, workers)
        console.print("[dim]dry run: nothing started[/]")
        return
    plan = sw.prepare(cfg, store, selection, retry_failed=retry_failed)
    left = cells_left(plan, cfg.sweep.max_retries)
    workers = min(workers, max(1, left))  # a worker per cell at most: more would only wait
    _print_plan(console, plan, cfg.sweep.max_retries, workers)
    if left == 0:
        raise typer.Exit(_final(console, plan, cfg.sweep.max_retries, 0 if plan.counts()["failed"] == 0 else 1))
    result = sw.run_pool(cfg, store, plan, workers=workers, console=console)
    if result.interrupted:
        console.print("[yellow]interrupted:[/] running cells were released; run the same command again to resume")
    bad = [c for c in result.worker_codes if c not in (0, 130)]
    if bad and not result.interrupted:
        console.print(f"[red]{len(bad)} worker(s) crashed[/] (exit codes {bad}); logs in {result.log_dir}")
    raise typer.Exit(_final(console, result.plan, cfg.sweep.max_retries, result.exit_code))


def _print_plan(console, plan, max_retries: int, workers: int) -> None:
    from ..sweep.status import plan_table  # lazy: keeps `bronchopose --help` fast

    console.print(plan_table(plan, max_retries))
    c = plan.counts()
    console.print(f"{len(plan.cells)} cells: {c['finished']} finished, {c['running']} running, {c['failed']} failed, "
                  f"{c['pending']} pending; workers here: {workers}")


def _final(console, plan, max_retries: int, code: int) -> int:
    from ..sweep.status import failures, progress, summary_line  # lazy: keeps `bronchopose --help` fast

    console.print(summary_line(progress(plan, max_retries, 1)))
    for label, reason in failures(plan):
        console.print(f"[red]failed[/] {label}: {reason}", highlight=False)
    return code
