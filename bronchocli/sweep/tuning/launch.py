"""``bronchopose tune``: a study's trials as rows of the claims table, run by sweep workers through the one driver.

``tune --trials N`` opens the study, adds the rows it lacks (``rows``:
sweep ``<study>.trials``, ``trial-0000`` ... ``trial-<N-1>``; raising N later
adds rows, lowering it removes none) and records on open rows the finished
trials no row records yet (a study older than its rows, or rebuilt from MLflow
after its storage was lost: ``record.rebuild_trials``), so none runs twice.
Then workers claim the rows, one Optuna trial per row (``worker``), started
by a launcher and watched by the sweep's driver (``launch.drive``) on every
machine: local worker processes placed on the GPUs (one worker without a GPU:
the local launcher runs it in this process, its own choice), Slurm array tasks
(``tune --launcher slurm``) or any registered launcher. The launcher is given
the config named after the study's rows, so its jobs are the study's (Slurm: job name
``bronchopose-<study>.trials``): ``bronchopose sweep cancel --study NAME``
stops them, ``bronchopose status --sweep <study>.trials`` shows the rows.

The study's parent MLflow run is RUNNING while ``tune`` runs and ends with the
study's outcome (``summary.log_study``): FINISHED, or KILLED when stopped
(Ctrl-C, ``sweep cancel``), FAILED on an error. Running ``tune`` again
continues: rows not finished are claimable again.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import replace
from typing import Any

from rich.console import Console

from ... import urls
from ...cells import Cell, TrialCell
from ...config import Config, Stage
from ...errors import BronchoError, ConfigError
from ...runs.client import client_for
from ...runs.contract import RunInterrupted
from ...runs.parents import KIND_STUDY, find_parent, set_parent_status, start_parent
from .. import launch as driver, summary
from ..launchers import launcher_class, reference
from ..launchers.base import Launcher
from ..plan import Plan, Step, cells_left, open_store, read_plan
from ..record import existing_experiment, rebuild_trials
from ..storage import FAILED, PENDING, SweepStore
from ..task import TaskSpec, command
from ..worker import EXIT_INTERRUPTED
from . import studies, trial
from .rows import StudyTask, study_sweep, trial_cell

log = logging.getLogger(__name__)

STAGE = Stage(name="trials")  # the one stage of a study's rows, as the driver and status name it
RECORDED = "recorded from the study"  # the worker column of a row recorded from a finished trial (``add_rows``)
# the launcher from its config (named after the rows), the task and the function making its workers' command
MakeLauncher = Callable[[Config, StudyTask, Callable[[], list[str]]], Launcher]


def launcher_config(cfg: Config, study: str) -> Config:
    """The config a study's launcher gets: named after its rows (``study_sweep``), so the launcher's jobs (their
    names, logs and comments follow the config's name) are the study's and ``sweep cancel --study`` finds them."""
    try:
        return cfg.with_values({"name": study_sweep(study)})
    except ConfigError:
        raise ConfigError(f"--study {study!r}: must start with a letter or digit and use only letters, digits, '.', "
                          "'_', '-' (it names the study's claims rows and jobs)") from None


def add_rows(cfg: Config, store: SweepStore, study: Any, target: Cell, trials: int) -> list[TrialCell]:
    """The study's rows: ``trials`` of them at least (none is removed), finished trials no row records yet
    recorded on open rows (``record_finished``); returns them all."""
    sweep = study_sweep(study.study_name)
    have = len(store.rows(sweep))
    rows = [trial_cell(target, i) for i in range(max(trials, have))]
    store.add_cells(sweep, rows)
    n = record_finished(store, sweep, study)
    if n:
        log.warning("study %s: %d finished trial(s) recorded on its claims rows (none runs again)",
                    study.study_name, n)
    return rows


def record_finished(store: SweepStore, sweep: str, study: Any) -> int:
    """Record each COMPLETE or PRUNED trial whose MLflow run no row names on an open (pending or failed) row."""
    stored = store.rows(sweep)
    named = {r.run_id for r in stored if r.run_id}
    done = [t.user_attrs[trial.ATTR_RUN] for t in study.get_trials(deepcopy=False, states=studies.FINISHED_STATES)
            if t.user_attrs.get(trial.ATTR_RUN) and t.user_attrs[trial.ATTR_RUN] not in named]
    open_rows = [r for r in stored if r.state in (PENDING, FAILED) and r.damage is None]
    return sum(1 for row, run_id in zip(open_rows, done) if store.record_finished(row, run_id, None, RECORDED))


class StudyWalk:
    """A study's rows walked as the driver walks a sweep's stages (``plan.StageWalk``'s members it uses): one
    stage, every cell known, nothing to settle."""

    complete = True

    def __init__(self, cfg: Config, store: SweepStore, rows: Sequence[TrialCell]):
        self.cfg, self.store, self.sweep = cfg, store, cfg.name  # cfg: the launcher's (``launcher_config``)
        self.stages, self._rows = [STAGE], list(rows)

    def cells(self, stage: Stage, *, mine: bool = True) -> list[TrialCell]:
        return self._rows

    def known_cells(self) -> list[TrialCell]:
        return self._rows

    def steps(self) -> Iterator[Step]:
        yield Step(STAGE, self._rows)

    def rows(self) -> Plan:
        return read_plan(self.store, self.sweep, self._rows)

    def work_left(self) -> list[tuple[Stage, int]]:
        return [(STAGE, cells_left(self.rows(), self.cfg.sweep.max_retries))]


def tune(cfg: Config, target: Cell, trials: int, *, study: str | None = None, timeout: float | None = None,
         make_launcher: MakeLauncher | None = None, spec: TaskSpec | None = None, progress: bool = True,
         enqueue: Sequence[Mapping[str, Any]] = (), console: Console | None = None) -> Any:
    """Run the study of ``target`` to ``trials`` rows done by the workers of the launcher ``make_launcher`` makes
    (None: the local launcher's one worker, which runs in this process), watched by the sweep's driver (a
    launcher whose workers run a command needs ``spec``, the config as the workers load it); ``progress``: the
    progress bars of a worker in this process. Returns the Optuna study. RunInterrupted when stopped; a failing study
    storage (read-only, damaged) is one line (``studies.storage_errors``)."""
    with studies.storage_errors(cfg):
        return _tune(cfg, target, trials, study=study, timeout=timeout, make_launcher=make_launcher, spec=spec,
                     progress=progress, enqueue=enqueue, console=console)


def _tune(cfg: Config, target: Cell, trials: int, *, study: str | None, timeout: float | None,
          make_launcher: MakeLauncher | None, spec: TaskSpec | None, progress: bool,
          enqueue: Sequence[Mapping[str, Any]], console: Console | None) -> Any:
    console = console or Console(quiet=True)
    trial.check_space(cfg)
    name = study or trial.study_name(cfg, target)
    lcfg = launcher_config(cfg, name)  # a bad --study: one line before anything is created
    s = trial.open_study(cfg, target, study=name)  # created once, before workers race
    rebuild_trials(cfg, s, trial.ATTR_RUN)  # a lost or new study storage: the trials MLflow records FINISHED count
    for params in enqueue:
        s.enqueue_trial(dict(params), skip_if_exists=True)
    store = open_store(cfg)
    store.ensure_schema()
    rows = add_rows(cfg, store, s, target, trials)
    task = StudyTask(name, cfg.name, None if timeout is None else time.time() + timeout, progress)
    parent = trial.study_parent_or_none(cfg, target, name)  # created here once, found by the workers
    client = client_for(cfg)
    if parent is not None:
        start_parent(client, parent)  # RUNNING with this process: `status --repair` ends it if killed
        summary.uncancel(client, parent)  # an explicit tune: a `sweep cancel --study` before it no longer holds
    make_launcher = make_launcher or _one_worker_here
    try:
        launcher = make_launcher(lcfg, task, lambda: _worker_command(lcfg, spec, task, type(launcher)))
        _launched(cfg, lcfg, store, rows, task, launcher, parent, console)
    except BaseException as exc:  # an interrupted or failed tune ends its parent run too (KILLED / FAILED)
        if parent is not None:
            interrupted = isinstance(exc, (KeyboardInterrupt, RunInterrupted))
            set_parent_status(client, parent, 130 if interrupted else 1)
        raise
    _close_parent(cfg, parent, s)
    return s


def _one_worker_here(lcfg: Config, task: StudyTask, command: Callable[[], list[str]]) -> Launcher:
    """The default: the local launcher with one worker and no GPU (it runs that worker in this process)."""
    return launcher_class("local")(lcfg, command, study=task, workers=1, gpus="none")


def _worker_command(lcfg: Config, spec: TaskSpec | None, task: StudyTask, kind: type[Launcher]) -> list[str]:
    """What each of a study's workers runs, for a launcher whose workers run a command (made at its first
    submission): the study's spec sealed; one line when the caller gave a loaded Config instead of a file."""
    if spec is None:
        raise BronchoError(f"tune --launcher {kind.name}: its workers load the config file themselves; give tune the "
                           "config file (not a loaded Config)")
    return command(lcfg, replace(spec, launcher=reference(kind), study=task.study, deadline=task.deadline))


def _launched(cfg: Config, lcfg: Config, store: SweepStore, rows: Sequence[TrialCell], task: StudyTask,
              launcher: Launcher, parent: str | None, console: Console) -> int:
    """The study's rows run by ``launcher``'s workers, watched by the driver; its exit code (130: RunInterrupted)."""
    launcher.check()  # before anything is submitted: one line
    client = client_for(cfg)
    console.print(f"[bold]study[/] {task.study}: trial rows {lcfg.name}, workers {launcher.describe()}",
                  highlight=False)
    code = driver.drive(StudyWalk(lcfg, store, rows), launcher, console, detach=False,
                        cancelled=lambda: summary.cancelled(client, parent),
                        cancel_hint=f"`bronchopose sweep cancel --study {task.study}`",
                        resume_hint="the same `bronchopose tune` command", what=f"study {task.study}")
    if code == EXIT_INTERRUPTED:
        raise RunInterrupted(f"tune interrupted: the study's workers were stopped (`sweep cancel`, Ctrl-C); running "
                             "trials were given back; run the same command to continue (workers: "
                             f"{launcher.describe()})")
    return code


def _close_parent(cfg: Config, parent: str | None, s: Any) -> None:
    """The study's outcome on its parent run (``summary.log_study``), which ends FINISHED (best effort)."""
    if parent is None:
        return
    client = client_for(cfg)
    try:
        summary.log_study(client, parent, studies.describe_study(s), studies.finished(s))
    except Exception as exc:  # noqa: BLE001 - the trials' runs and the study hold the results either way
        log.warning("could not record study %s on its parent run %s: %s", s.study_name, parent, exc)
    set_parent_status(client, parent, 0)


def cancel_study(cfg: Config, study: str, kind: type[Launcher], console: Console, *, dry_run: bool = False) -> int:
    """``sweep cancel --study NAME``: the study's parent run tagged cancelled (its `tune` stops watching and ends
    KILLED), then every queued or running worker of the study stopped (they give their rows back)."""
    lcfg = launcher_config(cfg, study)
    client, exp = existing_experiment(cfg)  # reads only: a name that is no study creates nothing
    parent = find_parent(client, exp.experiment_id, KIND_STUDY, study) if exp is not None else None
    if parent is None and not _has_rows(cfg, study):
        raise BronchoError(f"sweep cancel --study {study}: no such study (no parent run of it in experiment "
                           f"{cfg.experiment_name}, no trial rows in storage {urls.redact(cfg.paths.storage_url)}); "
                           "check the name")
    if parent is not None and not dry_run:
        summary.mark_cancelled(client_for(cfg), parent)
    return driver.cancel(kind(lcfg), console, dry_run=dry_run)


def _has_rows(cfg: Config, study: str) -> bool:
    """Whether the claims storage holds trial rows of ``study`` (reads only; no storage yet: none)."""
    store = open_store(cfg)
    return store.exists() and bool(store.rows(study_sweep(study)))
