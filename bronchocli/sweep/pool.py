"""Local worker processes of one ``bronchopose sweep`` and the parent's live view of the shared table.

Workers are ``multiprocessing`` processes started with ``spawn`` (a fresh
interpreter: no forked CUDA/MLflow/SQLAlchemy state, same behaviour on Linux
and macOS). Each takes at most cores / N torch threads (its share of the
cores beside every other process of the project: ``runs.cores``) so N
workers share the CPU instead of oversubscribing it, and logs to its own
file under ``sweep.logs``. The parent only watches: it polls the claims table
(so it also sees cells run by other machines) and the worker processes.

Ctrl-C: workers sit in their own process group, so the terminal's SIGINT
reaches the parent alone; it sets the shared stop event and sends every
worker one SIGTERM (a second Ctrl-C sends SIGINT: abort without waiting for
a checkpoint). Workers release their cells and exit 130; so does the parent.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import wait as wait_any
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live

from .. import urls
from ..config import Config
from ..errors import BronchoError
from .placement import assign, share_counts
from .plan import Plan, read_plan
from .status import live_view, progress, summary_line
from .storage import FINISHED, SweepStore
from .worker import EXIT_INTERRUPTED, Runner, WorkerSpec, default_runner, worker_process

REFRESH_S = 0.5


def worker_config(cfg: Config, workers: int) -> Config:
    """The config workers run with: no secrets in what MLflow logs (their CPU threads: ``WorkerSpec.cpu_workers``)."""
    values: dict[str, Any] = {"storage.url": urls.redact(cfg.storage.url)}
    return cfg.with_values(values)


def spawn_worker(spec: WorkerSpec, stop_event: Any = None) -> mp.Process:
    ctx = mp.get_context("spawn")
    proc = ctx.Process(target=worker_process, args=(spec, stop_event), name="bronchopose-sweep-worker")
    proc.start()
    return proc


@dataclass
class PoolResult:
    exit_code: int
    plan: Plan
    wall_s: float
    interrupted: bool
    worker_codes: list[int | None]
    log_dir: Path


class _ParentSignals:
    def __init__(self, procs: list[mp.Process], event: Any):
        self.procs, self.event, self.count = procs, event, 0

    def __call__(self, signum: int, frame: Any) -> None:
        self.count += 1
        self.event.set()
        forward = signal.SIGTERM if self.count == 1 else signal.SIGINT
        for p in self.procs:
            if p.is_alive() and p.pid:
                try:
                    os.kill(p.pid, forward)
                except ProcessLookupError:
                    pass


def run_pool(cfg: Config, store: SweepStore, plan: Plan, *, workers: int, runner: Runner = default_runner,
             console: Console | None = None, sweep: str | None = None, gpus: Sequence[str] = (),
             on_refresh: Callable[[Plan], None] | None = None) -> PoolResult:
    """Run every cell of ``plan`` with ``workers`` local processes (pinned round-robin to ``gpus``); returns when
    none is left to run here."""
    t0 = time.perf_counter()
    sweep = sweep or plan.sweep
    console = console or Console()
    log_dir = cfg.paths.sweep_logs / sweep
    log_dir.mkdir(parents=True, exist_ok=True)
    wcfg = worker_config(cfg, workers)
    event = mp.get_context("spawn").Event()
    procs: list[mp.Process] = []
    handler = _ParentSignals(procs, event)
    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        placed = assign(workers, gpus)
        for i, (gpu, share) in enumerate(zip(placed, share_counts(placed))):
            log_path = log_dir / f"{socket.gethostname()}-{os.getpid()}-w{i}.log"
            spec = WorkerSpec(wcfg, store.url, list(plan.cells), runner, sweep, os.getpid(), str(log_path), gpu,
                              share, cpu_workers=workers)
            procs.append(spawn_worker(spec, event))
        plan = _watch(store, plan, procs, cfg, workers, console, on_refresh)
    except BaseException:  # the parent is failing: stop the workers (they release their cells) before waiting
        if handler.count == 0:
            handler(signal.SIGTERM, None)
        raise
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        for p in procs:
            p.join()
    codes = [p.exitcode for p in procs]
    interrupted = handler.count > 0 or EXIT_INTERRUPTED in codes
    return PoolResult(_exit_code(plan, cfg.sweep.max_retries, interrupted), plan, time.perf_counter() - t0,
                      interrupted, codes, log_dir)


def _watch(store: SweepStore, plan: Plan, procs: list[mp.Process], cfg: Config, workers: int,
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
        while any(p.is_alive() for p in procs):
            wait_any([p.sentinel for p in procs if p.is_alive()], timeout=REFRESH_S)
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
