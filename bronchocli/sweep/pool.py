"""One stage of a local sweep: start its workers (``launchers.local``) and watch the shared table until they exit.

Each worker takes at most cores / N torch threads (its share of the cores
beside every other process of the project: ``runs.cores``) so N workers share
the CPU instead of oversubscribing it, and logs to its own file under
``sweep.logs``. The parent only watches: it polls the claims table (so it also
sees cells run by other machines) and the worker processes.

Ctrl-C: workers sit in their own process group, so the terminal's SIGINT
reaches the parent alone; it stops the workers once (``LocalProcesses.stop``:
the shared stop event and one SIGTERM each; a second Ctrl-C sends SIGINT: abort
without waiting for a checkpoint). Workers release their cells and exit 130;
so does the parent.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.live import Live

from ..cells import Selection
from ..config import Config
from ..errors import BronchoError
from .launchers.local import LocalLauncher, LocalProcesses
from .plan import Plan, read_plan
from .status import live_view, progress, summary_line
from .storage import FINISHED, SweepStore
from .worker import EXIT_INTERRUPTED, Runner, default_runner

REFRESH_S = 0.5


@dataclass
class PoolResult:
    exit_code: int
    plan: Plan
    wall_s: float
    interrupted: bool
    worker_codes: list[int | None]
    log_dir: Path


def run_pool(cfg: Config, store: SweepStore, plan: Plan, *, workers: int, runner: Runner = default_runner,
             console: Console | None = None, gpus: Sequence[str] = (), only: Selection | None = None,
             stage: str | None = None, on_refresh: Callable[[Plan], None] | None = None) -> PoolResult:
    """Run ``plan``'s cells (those of ``stage``, or of every stage, selected by ``only``) with ``workers`` local
    processes pinned round-robin to ``gpus``; returns when none is left to run here."""
    t0 = time.perf_counter()
    console = console or Console()
    launcher = LocalLauncher(cfg, storage_url=store.url, only=only, runner=runner, gpus=gpus,
                             log_dir=cfg.paths.sweep_logs / plan.sweep)
    procs = launcher.processes
    with procs.supervised():  # Ctrl-C stops the workers once; a failure here stops them before waiting
        launcher.submit(workers, stage or "")
        plan = _watch(store, plan, procs, cfg, workers, console, on_refresh)
    codes = procs.join()
    interrupted = procs.stops > 0 or EXIT_INTERRUPTED in codes
    return PoolResult(_exit_code(plan, cfg.sweep.max_retries, interrupted), plan, time.perf_counter() - t0,
                      interrupted, codes, procs.log_dir)


def _watch(store: SweepStore, plan: Plan, procs: LocalProcesses, cfg: Config, workers: int,
           console: Console, on_refresh: Callable[[Plan], None] | None) -> Plan:
    """Poll the table until every local worker has exited: a live view on a terminal, a line per change otherwise."""
    retries = cfg.sweep.max_retries
    live = None
    if console.is_terminal:
        live = Live(live_view(plan, retries, workers), console=console, refresh_per_second=4)
    last = ""

    def refresh() -> Plan:
        nonlocal last
        try:
            fresh = read_plan(store, plan.sweep, plan.cells)
            now = store.db_now()
        except BronchoError:  # a storage hiccup must not kill the watcher; workers retry on their own
            return plan
        if live is not None:
            live.update(live_view(fresh, retries, workers, now))
        elif (line := summary_line(progress(fresh, retries, workers)).plain) != last:
            console.print(line, highlight=False)
            last = line
        if on_refresh:
            on_refresh(fresh)
        return fresh

    if live is not None:
        live.start()
    try:
        while procs.sentinels():
            procs.wait(REFRESH_S)
            plan = refresh()
        return refresh()
    finally:
        if live is not None:
            live.stop()


def _exit_code(plan: Plan, max_retries: int, interrupted: bool) -> int:
    if interrupted:
        return EXIT_INTERRUPTED
    states = [plan.state(c) for c in plan.cells]
    return 0 if all(s == FINISHED for s in states) else 1
