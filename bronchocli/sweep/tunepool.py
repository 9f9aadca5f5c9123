"""``bronchopose tune``'s workers: the study's trials here, or in local worker processes placed like a sweep's.

One worker runs in this process. Several are the sweep's local processes
(``launchers.local.LocalProcesses``): pinned round-robin to the GPUs of
``--gpus`` (``--per-gpu`` of them on each; default GPUs x per-GPU, else 1),
each with its share of the cores, its own log file under ``sweep.logs/<study>``
and its stop signals: the terminal's Ctrl-C reaches this process alone, which
stops every worker once (SIGTERM: the trial in progress checkpoints and ends
KILLED, no other starts; a second Ctrl-C sends SIGINT). Each trial records the
worker that ran it (``tuning.ATTR_WORKER``: host, pid and GPU).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ..cells import Cell
from ..config import Config
from ..errors import BronchoError
from ..runs.client import client_for
from ..runs.contract import RunInterrupted
from ..runs.parents import set_parent_status, start_parent
from . import tuning
from .launchers.local import LocalLauncher, LocalProcesses
from .record import rebuild_trials
from .stagework import exit_process, start_worker
from .summary import log_study
from .worker import EXIT_INTERRUPTED

log = logging.getLogger(__name__)


@dataclass
class TuneJob:
    """What one tune worker process needs (picklable)."""

    cfg: Config
    target: Cell
    trials: int
    study: str | None
    timeout: float | None
    worker: int  # its index: a different sampler seed per worker
    gpu: str | None = None
    gpu_share: int = 1
    log_path: str | None = None
    parent_pid: int | None = None
    cpu_workers: int = 1


def tune_process(job: TuneJob, stop_event: Any = None) -> None:
    """A tune worker process: trials until the study holds ``trials`` finished ones; exit 0, 130 (stopped) or 2."""
    _, signals = start_worker(job, LocalLauncher, stop_event)  # placed, logged and stopped like a sweep's worker
    log.info("tune worker %d of study %s, CUDA_VISIBLE_DEVICES=%s", job.worker, job.study or "(the cell's)",
             os.environ.get("CUDA_VISIBLE_DEVICES", "unset"))

    def trials() -> int:
        try:
            tuning.tune_worker(job.cfg, job.target, job.trials, study=job.study, timeout=job.timeout,
                               worker=job.worker, stop=lambda: signals.stop)
        except (KeyboardInterrupt, RunInterrupted):
            return EXIT_INTERRUPTED
        return EXIT_INTERRUPTED if signals.requested is not None else 0

    exit_process(trials)


def tune(cfg: Config, target: Cell, trials: int, *, study: str | None = None, timeout: float | None = None,
         workers: int = 1, gpus: Sequence[str] | None = None, progress: bool = True,
         enqueue: Sequence[Mapping[str, Any]] = ()) -> Any:
    """Tune with ``workers`` (1 and no ``gpus``: in this process; else local processes on ``gpus``); returns the
    study.

    The study's parent MLflow run is created before the workers start and ends with the best trial's
    validation loss as its metric ``val_best.loss`` (tags ``best_trial``, ``best_run``).
    """
    tuning.check_space(cfg)
    s = tuning.open_study(cfg, target, study=study)  # creates it once, before workers race
    rebuild_trials(cfg, s, tuning.ATTR_RUN)  # a lost or new study storage: the trials MLflow records FINISHED count
    parent = tuning.study_parent_or_none(cfg, target, s.study_name)  # created here once, found by the workers
    if parent is not None:
        start_parent(client_for(cfg), parent)  # RUNNING with this process: `status --repair` ends it if killed
    try:
        if workers <= 1 and not gpus:
            tuning.tune_worker(cfg, target, trials, study=study, timeout=timeout, progress=progress, enqueue=enqueue)
        else:
            for params in enqueue:
                s.enqueue_trial(dict(params), skip_if_exists=True)
            run_workers(cfg, target, trials, s.study_name, study=study, timeout=timeout, workers=workers,
                        gpus=gpus or ())
    except BaseException as exc:  # an interrupted or failed tune ends its parent run too (KILLED / FAILED)
        if parent is not None:
            interrupted = isinstance(exc, (KeyboardInterrupt, RunInterrupted))
            set_parent_status(client_for(cfg), parent, 130 if interrupted else 1)
        raise
    _close_parent(cfg, target, s)
    return s


def run_workers(cfg: Config, target: Cell, trials: int, name: str, *, study: str | None, timeout: float | None,
                workers: int, gpus: Sequence[str]) -> None:
    """``workers`` tune processes on ``gpus`` until they exit; RunInterrupted when they were stopped."""
    procs = LocalProcesses(cfg.paths.sweep_logs / name, gpus, name="bronchopose-tune-worker")
    index = iter(range(workers))

    def job(gpu: str | None, share: int, log_path: str) -> TuneJob:
        return TuneJob(cfg, target, trials, study, timeout, next(index), gpu, share, log_path, os.getpid(), workers)

    with procs.supervised():  # the local launcher's stop signals and failure handling
        procs.start(workers, tune_process, job)
        while procs.sentinels():
            procs.wait()
    codes = procs.join()
    if procs.stops or EXIT_INTERRUPTED in codes:
        raise RunInterrupted(f"tune interrupted: the trials in progress were stopped (logs in {procs.log_dir}); "
                             "run the same command to continue")
    bad = [c for c in codes if c != 0]
    if bad:
        raise BronchoError(f"{len(bad)} tune worker(s) failed (exit codes {bad}); logs in {procs.log_dir}")


def _close_parent(cfg: Config, target: Cell, s: Any) -> None:
    """The study's outcome on its parent run (``summary.log_study``), which ends FINISHED (best effort)."""
    parent = tuning.study_parent_or_none(cfg, target, s.study_name)
    if parent is None:
        return
    client = client_for(cfg)
    try:
        log_study(client, parent, tuning.describe_study(s), tuning.finished(s))
    except Exception as exc:  # noqa: BLE001 - the trials' runs and the study hold the results either way
        log.warning("could not record study %s on its parent run %s: %s", s.study_name, parent, exc)
    set_parent_status(client, parent, 0)
