"""The one worker entry every launcher starts: ``worker_main`` runs one sweep worker through the stages.

A local worker process (``launchers.local``) and a detached one (a Slurm array
task, a test's subprocess worker: ``python -m bronchocli.sweep.task <spec>``)
both end up here with a ``WorkerJob``: pinned to its GPU (``placement.pin_env``,
before anything imports torch), its output in its log file, its stop signals
installed (and its launcher's warning signal, e.g. Slurm's SIGUSR1: ``Launcher.Environment``), its ``WorkerId``
(host, pid, the launcher's job id, GPU) on every claim and log line. It walks
the stages in order (``work_stages``): claims the first stage's cells; goes on
to a later stage only once every cell before it is done, settling its selection
first; stops after the stage it was submitted for. A tuning study's worker
(``WorkerJob.study``) claims the study's trial rows instead (``tuning.worker``). Exit code 0 (nothing left
here), 130 (stopped), 2 (a user error, logged in one line), 3 (stopped after a failure recorded on its cell's
row: a full disk; the cell's failure says it).
"""

from __future__ import annotations

import logging
import os
import socket
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NoReturn

from .. import interrupts, urls
from ..cells import Selection
from ..config import Config
from ..errors import BronchoError, WriteFailed
from ..runs.client import client_for, experiment_id
from ..runs import cores
from ..runs.parents import KIND_SWEEP, find_parent, set_parent_status, sweep_parent
from . import plan as planning
from .liveness import StopSignals
from .placement import pin_env
from .selection import describe_selection
from .storage import FINISHED, RUNNING, SweepStore
from .tuning.rows import StudyTask
from .summary import TAG_CANCELLED, cancelled, record_stop, reopen
from .worker import EXIT_INTERRUPTED, EXIT_OK, EXIT_RECORDED, Runner, Worker, WorkerId, default_runner, job_of

if TYPE_CHECKING:  # the launchers start workers through this module (local imports it): it names them, never imports
    from .launchers.base import Launcher, WorkerEnvironment

log = logging.getLogger(__name__)

GPU_ENV = "BRONCHOPOSE_WORKER_GPU"  # the GPU a local worker was pinned to (its WorkerId shows it)


def worker_config(cfg: Config) -> Config:
    """The config workers run with: no secrets in what MLflow logs (their CPU threads: ``WorkerJob.cpu_workers``)."""
    return cfg.with_values({"storage.url": urls.redact(cfg.storage.url)})


@dataclass
class WorkerJob:
    """Everything one worker needs, whichever launcher started it (picklable: local workers get it by spawn)."""

    cfg: Config  # storage URL redacted: the config is logged to MLflow
    storage_url: str  # the real one
    only: Selection
    launcher: type[Launcher]  # its worker side (``Launcher.environment``): job id, threads, warning signal, ...
    runner: Runner = default_runner
    last_stage: str | None = None  # stop after this stage (None: every stage)
    exit_when_idle: bool = True  # exit when nothing is claimable now instead of waiting for cells held elsewhere
    ends_parent: bool = True  # the last stage done: end the sweep's parent run (no watcher may be left to do it)
    log_path: str | None = None  # stdout and stderr go there (None: left as they are)
    gpu: str | None = None  # this worker's GPU (its CUDA_VISIBLE_DEVICES); None: the environment is left alone
    gpu_share: int = 1  # workers pinned to that GPU (this one included)
    parent_pid: int | None = None  # a local worker: its own process group; it stops when that process is gone
    cpu_workers: int = 1  # workers its command runs on this machine: each takes at most cores / N (runs.cores)
    study: StudyTask | None = None  # a tuning study's worker: its trial rows instead of the stages (``tuning.worker``)


def this_worker(launcher: type[Launcher], env: WorkerEnvironment) -> WorkerId:
    """This process as a claims row and a log line name it."""
    job = env.job_id
    gpu = os.environ.get(GPU_ENV) or (os.environ.get("CUDA_VISIBLE_DEVICES") if job else None)
    return WorkerId(socket.gethostname(), os.getpid(), launcher.name if job else None, job, gpu or None)


def _redirect_output(path: str | None) -> None:
    if path is None:
        return
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    sys.stdout.flush()
    sys.stderr.flush()
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)


def prepare_process(gpu: str | None, share: int, log_path: str | None, parent_pid: int | None,
                    cpu_workers: int) -> None:
    """A worker process's first steps, before anything imports torch: its share of the cores (``runs.cores``),
    its GPU (``placement.pin_env``: the run sees one device, cuda:0), its own process group (a local worker: the
    terminal's Ctrl-C reaches the parent only, which stops the workers once, with SIGTERM), its log file."""
    os.environ[cores.WORKERS_ENV] = str(max(1, cpu_workers))  # each takes at most cores / workers threads
    if gpu is not None:
        for key, value in pin_env(gpu, share).items():
            if key != "CUDA_DEVICE_ORDER" or key not in os.environ:  # a user's own device order stands
                os.environ[key] = value
        os.environ[GPU_ENV] = gpu
    if parent_pid is not None:
        os.setpgrp()
    _redirect_output(log_path)


def start_worker(job: WorkerJob, launcher: type[Launcher], stop_event: Any,
                 env: WorkerEnvironment | None = None) -> tuple[WorkerId, StopSignals]:
    """A worker process's start, a sweep's or a study's: ``prepare_process``, its ``WorkerId`` on every log line
    of its log file, its stop signals (and ``launcher``'s warning signal) installed. ``env``: the launcher's
    worker environment (default: built from ``job.cfg``)."""
    prepare_process(job.gpu, job.gpu_share, job.log_path, job.parent_pid, job.cpu_workers)
    env = env or launcher.environment(job.cfg)
    ident = this_worker(launcher, env)
    if job.log_path is not None:
        logging.basicConfig(level=logging.INFO, stream=sys.stderr, force=True,
                            format=f"%(asctime)s {ident} %(levelname)s %(name)s: %(message)s")
    signals = StopSignals(stop_event, job.parent_pid)
    signals.install(extra=(env.warning_signal,) if env.warning_signal is not None else ())
    return ident, signals


def exit_process(main: Callable[[], int]) -> NoReturn:
    """A spawned worker process's end: run ``main`` and exit with its code; a user error (BronchoError) is logged
    in one line (passwords redacted) and exits with its code (2)."""
    code = EXIT_INTERRUPTED
    try:
        code = main()
    except BronchoError as exc:
        log.error("%s", urls.redact(str(exc)))
        code = exc.exit_code
    finally:
        logging.shutdown()
    sys.exit(code)


def worker_main(job: WorkerJob, stop_event: Any = None) -> int:
    """Run one worker through the stages; its exit code (0 nothing left here, 130 stopped). A training run stops on
    the launcher's warning signal too, its KILLED reason naming what sent it (``interrupts.warned_by``)."""
    env = job.launcher.environment(job.cfg)
    with interrupts.warned_by(env.warning_signal, env.warning_meaning):
        return _worker_main(job, env, stop_event)


def _worker_main(job: WorkerJob, env: WorkerEnvironment, stop_event: Any) -> int:
    ident, signals = start_worker(job, job.launcher, stop_event, env)
    cfg = job.cfg
    if cfg.train.threads is None and (threads := env.threads):
        cfg = cfg.with_values({"train.threads": threads})
    title, _, task_word = job.launcher.Session.words(job.launcher.name)
    log.info("%s, %s %s %s, CUDA_VISIBLE_DEVICES=%s",
             f"tune worker of study {job.study.study}" if job.study else f"sweep worker {cfg.name}",
             title, task_word, ident.job or ident, os.environ.get("CUDA_VISIBLE_DEVICES", "unset"))
    code, store = EXIT_INTERRUPTED, None
    # no watcher may be left to keep a detached sweep's parent run true (a study's: its `tune` command ends it)
    detached = job.ends_parent and job.launcher.Session.outlives_command and job.study is None
    try:
        store = planning.open_store(cfg, job.storage_url)
        if detached:
            reopen_parent(cfg)
        if job.study is not None:
            from .tuning.worker import work_trials  # lazy: Optuna loads only in a study's workers

            code, _ = work_trials(cfg, store, job.study, signals=signals, ident=str(ident),
                                  exit_when_idle=job.exit_when_idle, storage_url=job.storage_url)
        else:
            code = work_stages(cfg, store, job.only, signals=signals, runner=job.runner,
                               exit_when_idle=job.exit_when_idle, last_stage=job.last_stage, ident=str(ident),
                               ends_parent=job.ends_parent)
    except KeyboardInterrupt:
        code = EXIT_INTERRUPTED
    except WriteFailed as exc:
        if getattr(exc, "recorded_on", None) is None:
            raise
        log.error("stopped: %s failed on a full disk (recorded on its cell, no attempt spent; every other cell would "
                  "meet it): %s", exc.recorded_on, urls.redact(str(exc)))
        code = EXIT_RECORDED
    finally:  # a user error (BronchoError) goes on to the caller: one line where its output is read
        env.done(signals.requested)
        if detached and store is not None:
            settle_parent(cfg, store, job.only, job.launcher, env, signals)
    return code


def local_process(job: WorkerJob, stop_event: Any = None) -> None:
    """A spawned local worker process: ``worker_main``, then exit with its code (a user error: logged, 2)."""
    exit_process(lambda: worker_main(job, stop_event))


def work_stages(cfg: Config, store: SweepStore, only: Selection, *, signals: StopSignals,
                runner: Runner = default_runner, exit_when_idle: bool = True, last_stage: str | None = None,
                ident: str | None = None, ends_parent: bool = True) -> int:
    """One worker taking the stages in order: claim the first stage's cells; go on to a later stage only once
    every cell before it is done, settling its selection first (recorded once, whichever worker gets there
    first). Returns when nothing is left here: with ``exit_when_idle`` this worker does not wait for cells running
    elsewhere (later stages' workers start when those end).

    With ``last_stage`` (the stage the worker was submitted for) the worker stops after that stage: the later
    stages have workers of their own, sized to their cells, which would otherwise find them taken. It never
    takes an earlier stage's work either: a worker that finds an earlier stage unfinished (its workers were
    cancelled, and a dependency on them let this one start) exits at once, leaving those cells to that stage's
    workers (issue 37: a stage-2 task started before the re-submitted stage 1 ran stage 1's cells)."""
    names = [s.name for s in planning.stages_of(cfg)]
    if last_stage is not None and last_stage not in names:
        raise BronchoError(f"this task was submitted for stage {last_stage!r}, which the config's stages no longer "
                           f"have ({', '.join(names)}); run `bronchopose sweep cancel` and submit again")
    for step in planning.StageWalk(cfg, store, only).steps():
        if step.waits:
            log.info("stage %s waits: %d cell(s) of stage %s are not done", step.stage.name, step.waits,
                     step.source.name)
            return EXIT_OK
        if step.settled is not None:
            log.info("%s", describe_selection(step.settled))
        if step.cells:
            plan = planning.ensure_rows(cfg, store, step.cells)
            if (last_stage is not None and names.index(step.stage.name) < names.index(last_stage)
                    and (left := planning.cells_left(plan, cfg.sweep.max_retries))):
                log.info("stage %s is not done (%d cell(s) left): this worker was submitted for stage %s and leaves "
                         "them to stage %s's workers; exiting", step.stage.name, left, last_stage, step.stage.name)
                return EXIT_OK
            worker = Worker(cfg, step.cells, store, runner, signals=signals, exit_when_idle=exit_when_idle,
                            ident=ident)
            code = worker.run()
            if code != EXIT_OK or worker.idle:
                if worker.idle:
                    log.info("nothing to claim in stage %s (its other cells run elsewhere): exiting", step.stage.name)
                return code
        if step.stage.name == last_stage and last_stage != names[-1]:
            log.info("stage %s done here: later stages are left to their own workers", last_stage)
            return EXIT_OK
    if ends_parent:
        end_parent(cfg, store, only)  # every stage done: a detached sweep has no watcher to end its parent run
    return EXIT_OK


def end_parent(cfg: Config, store: SweepStore, only: Selection) -> None:
    """End the sweep's parent run like the sweep: FINISHED when every cell finished, else FAILED (best effort)."""
    plan = planning.StageWalk(cfg, store, only).rows()
    code = 0 if all(plan.state(c) == FINISHED for c in plan.cells) else 1
    try:
        client = client_for(cfg)
        parent = sweep_parent(client, cfg, experiment_id(client, cfg))
        if cancelled(client, parent):  # `sweep cancel` ended it KILLED: a worker that got to the end leaves it so
            return
        set_parent_status(client, parent, code)
    except Exception as exc:  # noqa: BLE001 - the cells carry the results; logged
        log.warning("could not end the sweep's parent run: %s", exc)


def reopen_parent(cfg: Config) -> None:
    """A detached worker starting on a sweep whose last worker had stopped it (``settle_parent``): its parent run
    is RUNNING again (best effort)."""
    try:
        client = client_for(cfg)
        parent = find_parent(client, experiment_id(client, cfg), KIND_SWEEP, cfg.name)
        if parent is not None and reopen(client, parent):
            log.info("sweep %s's parent run %s is RUNNING again", cfg.name, parent)
    except Exception as exc:  # noqa: BLE001 - the cells carry the results; logged
        log.warning("could not read the sweep's parent run: %s", exc)


def settle_parent(cfg: Config, store: SweepStore, only: Selection, launcher: type[Launcher], env: WorkerEnvironment,
                  signals: StopSignals) -> None:
    """A detached worker leaving (``end_abandoned``): left alone when stopped by its launcher's warning signal
    (Slurm's time limit: it is requeued, or its watcher submits another)."""
    if not env.warned(signals.requested):
        end_abandoned(cfg, store, only, launcher, me={env.job_id, str(os.getpid())})


def end_abandoned(cfg: Config, store: SweepStore, only: Selection | None, launcher: type[Launcher], *,
                  me: set[str | None] | None = None) -> str | None:
    """End the sweep's parent run when nothing else would (issue 50: `sweep run --detach`, then `scancel` of stage 1,
    left it RUNNING until the next run): it is RUNNING, no worker of the sweep is queued or running
    (``launcher.active``; ``me``: the worker asking, as its launcher lists it), none started by hand holds a live
    claim, and cells are not done. It ends KILLED (cells left: `sweep run` resumes them) or FAILED (every cell
    done, some failed for good), the reason as its ``sweep_stopped`` tag, logged; returns that reason (None: left
    alone, as a parent no longer RUNNING: finished, or ``sweep cancel``). Asked by each detached worker as it
    leaves, and by ``bronchopose status`` (``entry.settle_detached``)."""
    try:
        client = client_for(cfg)
        parent = find_parent(client, experiment_id(client, cfg), KIND_SWEEP, cfg.name)
        run = client.get_run(parent) if parent is not None else None
        if run is None or run.info.status != "RUNNING" or TAG_CANCELLED in run.data.tags:
            return None
        me = me or set()
        others = [t for t in launcher(cfg).active()
                  if not t.ending and not (t.id in me and t.state == "RUNNING")]  # requeued: comes back, counts
        if others:
            return None
        walk = planning.StageWalk(cfg, store, only)
        plan, now = walk.rows(), store.db_now()
        if any(r.state == RUNNING and job_of(r.worker) is None and r.heartbeat is not None
               and r.heartbeat >= now - cfg.sweep.stale_after_s for r in plan.rows.values()):
            return None  # a worker started by hand (no job of this launcher) still runs a cell: it ends the sweep
        left = planning.cells_left(plan, cfg.sweep.max_retries)
        if not left and walk.complete and all(plan.state(c) == FINISHED for c in plan.cells):
            set_parent_status(client, parent, 0)
            return None
        code = EXIT_INTERRUPTED if left or not walk.complete else 1
        title, _, task_word = launcher.Session.words(launcher.name)
        reason = (f"no {title} {task_word} of sweep {cfg.name} is queued or running and "
                  + (f"{f'{left} cell(s) are' if left else 'a later stage is'} not done (its {task_word}s "
                     "were stopped: `scancel`, a node gone); "
                     "`bronchopose sweep run` resumes it" if code == EXIT_INTERRUPTED else
                     "every cell is done, some failed for good; `bronchopose sweep run --retry-failed` runs them "
                     "again"))
        record_stop(client, parent, reason, code)
        log.warning("sweep %s's parent run %s ends %s: %s", cfg.name, parent,
                    "KILLED" if code == EXIT_INTERRUPTED else "FAILED", reason)
        return reason
    except Exception as exc:  # noqa: BLE001 - the cells carry the results; logged
        log.warning("could not settle the sweep's parent run: %s", exc)
        return None
