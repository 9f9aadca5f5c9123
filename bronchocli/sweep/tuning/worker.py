"""A tuning study's worker: claim a trial row of the claims table, run one Optuna trial for it, record the outcome.

A study of N trials is N rows of the claims table (``rows``: sweep
``<study>.trials``, keys ``trial-0000``, ...; added by ``launch``). Any sweep
worker (``sweep.worker.Worker``, started by any launcher through
``stagework.worker_main`` with a ``StudyTask``) claims them: for each row it
claims it asks the study for one trial (a WAITING one first: a stopped trial's
checkpoint handed on, ``resume``), trains it through ``trial.objective``
with the worker's heartbeat, and records the trial's MLflow run on the row. A
complete or pruned trial finishes its row; a failed one fails it (retried as a
sweep's cells are, ``sweep.max_retries``); a stop signal releases it (the trial
ends FAIL in Optuna and its checkpoint goes to a WAITING trial that the next
claim of any row resumes). The claims table thus decides how many trials run:
exactly one per row.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

import optuna

from ... import cells
from ...cells import TrialCell
from ...config import Config
from ...errors import BronchoError
from ..liveness import StopSignals
from ..storage import SweepStore
from ..worker import EXIT_OK, TAG_WORKER, Worker
from .rows import StudyTask, study_sweep
from .trial import ATTR_RUN, TrialFailed, objective, open_study, study_parent_or_none

log = logging.getLogger(__name__)


@dataclass
class TrialResult:
    """What the Worker records on a trial's row (``runs.contract.RunResult``'s fields that it reads)."""

    run_id: str | None
    status: str  # FINISHED (complete or pruned) or FAILED
    failure_reason: str | None = None
    duration_s: float | None = None
    stop_requested: int | None = None  # a stop signal that arrived while the trial evaluated


HEARTBEAT_TARGET = "HeartbeatThread._record_heartbeat"  # optuna.storages._heartbeat: the trial's heartbeat loop


def end_heartbeats(timeout_s: float = 5.0) -> int:
    """Stop the Optuna trial heartbeat threads still running in this process; how many were stopped.

    Optuna starts a trial's heartbeat (a non-daemon thread) in the ``__enter__`` of a ``with`` around the trial and
    stops it in ``__exit__``. A stop signal that lands between the thread's start and the ``with`` body (our
    handlers raise) skips ``__exit__``: the thread then runs for ever and the worker process hangs at interpreter
    shutdown, waiting for it. After a trial raised, every such thread is told to stop (its stop event, the third
    argument of its target) and joined."""
    stopped = 0
    for thread in threading.enumerate():
        target, args = getattr(thread, "_target", None), getattr(thread, "_args", ())
        if getattr(target, "__qualname__", "") != HEARTBEAT_TARGET or len(args) < 3 \
                or not isinstance(args[2], threading.Event):
            continue
        args[2].set()
        thread.join(timeout_s)
        stopped += not thread.is_alive()
    return stopped


class TrialRunner:
    """The runner a study's worker hands each claimed row to (the Worker's runner signature): one Optuna trial.

    ``stopped``: the trial number and signal of the last stop (a signal during its training, or one that arrived
    while it evaluated): the tune command's message says which trial it was."""

    def __init__(self, study: str, parent: str | None, progress: bool = False, storage_url: str | None = None):
        """``storage_url``: the real one where the worker's config has it redacted (the config is logged)."""
        self.study, self.parent, self.progress, self.storage_url = study, parent, progress, storage_url
        self.stopped: tuple[int | None, BaseException | int] | None = None

    def __call__(self, cfg: Config, cell: TrialCell, *, extra_tags: dict[str, str], run_id_callback: Any,
                 owns: Any = None, **_: Any) -> TrialResult:
        target = cell.target()
        at = cfg.with_values({"storage.url": self.storage_url}) if self.storage_url else cfg
        s = open_study(at, target, study=self.study, worker=cell.trial)  # a sampler seed per slot
        fn = objective(cfg, target, self.study, parent=self.parent, worker=extra_tags.get(TAG_WORKER, ""),
                       extra_tags=extra_tags, progress=self.progress, run_id_callback=run_id_callback, owns=owns)
        numbers: list[int] = []

        def one(trial) -> float:
            numbers.append(trial.number)
            return fn(trial)

        t0 = time.perf_counter()
        try:
            s.optimize(one, n_trials=1, catch=(TrialFailed,))
        except BaseException as exc:  # a stop (the row is released) or an error (the row fails): the Worker says
            self.stopped = (numbers[-1] if numbers else None, exc)
            end_heartbeats()
            raise
        if not numbers:  # Optuna started no trial: the row fails with this reason (retried as any failure)
            raise BronchoError(f"study {self.study}: Optuna started no trial")
        trial = next(t for t in s.get_trials(deepcopy=False) if t.number == numbers[-1])
        run_id = trial.user_attrs.get(ATTR_RUN)
        if fn.stop_requested:
            self.stopped = (trial.number, fn.stop_requested)
        if trial.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED):
            log.info("trial %d of study %s %s (row %s, run %s)", trial.number, self.study, trial.state.name.lower(),
                     cell.key, run_id)
            return TrialResult(run_id, "FINISHED", duration_s=time.perf_counter() - t0,
                               stop_requested=fn.stop_requested)
        reason = trial.system_attrs.get("fail_reason") or f"trial {trial.number} ended {trial.state.name}"
        return TrialResult(run_id, "FAILED", f"trial {trial.number}: {reason}", stop_requested=fn.stop_requested)


class TrialWorker(Worker):
    """A sweep worker over a study's rows: its runs nest under the study's parent run (not a sweep's), and with a
    deadline it gives back the rows it claims once the deadline passed (``tune --timeout``)."""

    def __init__(self, cfg: Config, rows: list[TrialCell], store: SweepStore, runner: TrialRunner, *,
                 deadline: float | None = None, **kw: Any):
        super().__init__(cfg, rows, store, runner, **kw)
        self._parent = runner.parent
        self.deadline, self.timed_out = deadline, False

    def parent_run(self) -> str | None:
        return self._parent

    def run(self) -> int:
        if self._past_deadline():  # a worker started after it claims nothing (a launcher's top-up ends there)
            return EXIT_OK
        return super().run()

    def _past_deadline(self) -> bool:
        self.timed_out = self.deadline is not None and time.time() >= self.deadline
        return self.timed_out

    def _handle(self, claim: Any) -> str:
        if self._past_deadline():
            self._db(self.store.release, claim.token)
            log.info("the study's deadline passed (tune --timeout): %s given back, no trial started", claim.row.label)
            return "stop"
        return super()._handle(claim)


def stored_rows(store: SweepStore, study: str) -> list[TrialCell]:
    """The study's trial rows as cells (a damaged row is left to the Worker, which sets it aside)."""
    out = []
    for row in store.rows(study_sweep(study)):
        try:
            cell = cells.make(**row.coords, key=row.cell_key)
        except Exception:  # noqa: BLE001 - coords that name no cell: not this code's row, never claimed
            continue
        if isinstance(cell, TrialCell):
            out.append(cell)
    return out


def work_trials(cfg: Config, store: SweepStore, task: StudyTask, *, signals: StopSignals | None = None,
                ident: str | None = None, exit_when_idle: bool = False, progress: bool = False,
                storage_url: str | None = None) -> tuple[int, TrialWorker | None]:
    """One worker through the study's rows until none is left to claim (``exit_when_idle``: none claimable now);
    its exit code (0, or 130 stopped) and the worker (its runner's ``stopped``, ``timed_out``). ``storage_url``: the
    real one where ``cfg``'s is redacted (a worker's config: it is logged)."""
    if cfg.name != task.config:  # the launcher's config names the study's rows; trials run under the config's name
        cfg = cfg.with_values({"name": task.config})
    rows = stored_rows(store, task.study)
    if not rows:
        log.warning("study %s has no trial rows in the claims table (sweep %s): nothing to do", task.study,
                    study_sweep(task.study))
        return 0, None
    parent = study_parent_or_none(cfg, rows[0].target(), task.study)
    runner = TrialRunner(task.study, parent, progress, storage_url if storage_url != cfg.storage.url else None)
    worker = TrialWorker(cfg, rows, store, runner, deadline=task.deadline,
                         signals=signals, sweep=study_sweep(task.study), ident=ident, exit_when_idle=exit_when_idle)
    code = worker.run()
    return (0 if worker.timed_out else code), worker


def stopped_line(stopped: tuple[int | None, Any] | None) -> str:
    """Why a study's worker stopped (its runner's ``stopped``: the trial and the signal or error), in one line."""
    if stopped is None:
        return "tune interrupted; run the same command to continue"
    number, why = stopped
    if isinstance(why, int):
        return (f"tune interrupted (signal {why} while trial #{number} was evaluated: that trial was completed "
                "first, no other was started); run the same command to continue")
    return f"tune interrupted: trial #{number} stopped ({why}); run the same command to continue"
