"""A sweep worker: claim a cell, run it with a heartbeat, record the outcome only while still holding the claim.

The cell runner is injectable: any function with ``run_cell``'s signature,
``runner(cfg, cell, *, extra_tags, progress, run_id_callback) -> runs.contract.RunResult``.
The real one trains (``default_runner``); ``bronchopose sweep run --runner
module:function`` names another (``task.load_runner``), which reaches spawned
worker processes by reference and Slurm array tasks through their task spec;
tests and benchmarks use it for fast fakes. Workers are started by a launcher
(``launchers``), each through the one worker entry (``stagework.worker_main``).

Signals: SIGINT/SIGTERM (and a launcher's own, e.g. SIGUSR1 in a Slurm task) stop the worker. While a
cell trains, ``run_cell`` itself turns the signal into a checkpoint of the
current step and a KILLED MLflow run (``RunInterrupted``, which carries the
signal back here); outside its training loop the worker raises
``KeyboardInterrupt`` into the runner.
Either way the cell is released (pending again, attempt not counted) and the
worker exits with 130. When the heartbeat finds the claim taken over (this
worker looked dead), the worker interrupts its own run with SIGTERM, marks the
run KILLED and goes on with another cell.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..cells import Cell
from ..config import Config
from ..errors import BronchoError, MlflowUnreachable, WriteFailed, resumable
from ..retry import retry
from ..runs.client import MlflowBusy, client_for, experiment_id
from ..runs.contract import RunTakenOver, checkpoint_dir, failure_reason, resume_file
from ..runs.ownership import remove_checkpoint
from ..runs.parents import sweep_parent
from ..runs.records import TAG_CELL_KEY, TAG_FAILURE, TAG_PARENT, search_runs
from .damage import damage_line, damaged, future_line
from .liveness import FutureHeartbeats, Heartbeat, StopSignals, is_interrupt
from .record import duration_of, finished_runs
from .session import EXIT_INTERRUPTED
from .storage import TAG_CLAIM, CellRow, Claim, StorageError, SweepStore

log = logging.getLogger(__name__)

TAG_WORKER = "sweep_worker"
TAG_ATTEMPT = "sweep_attempt"
EXIT_OK = 0  # and EXIT_INTERRUPTED, 130: defined in ``session`` (which the launchers' registry reads without this)
EXIT_RECORDED = 3  # stopped after a failure recorded on its cell's row (a full disk): reported there, not a crash

Runner = Callable[..., Any]  # run_cell's signature; returns an object with run_id, status, failure_reason, duration_s


def default_runner(cfg: Config, cell: Cell, **kw: Any) -> Any:
    """Train the cell (``training.run.run_cell``)."""
    from ..training.run import run_cell  # lazy: torch loads in worker processes only, not in the sweep's parent

    return run_cell(cfg, cell, **kw)


@dataclass(frozen=True)
class WorkerId:
    """Who holds a claim: host, pid, the launcher and its job for this worker (Slurm: ``812_3``), the GPU.

    Stored in the claims row as its text, ``host:pid [<launcher> <job>] [gpu<id>]`` (``node7:4242 slurm 812_3
    gpu0``), which ``parse`` reads back (the one reader: ``status`` and the watch ask it for the job)."""

    host: str
    pid: int
    launcher: str | None = None  # a launcher whose workers have a job id of their own (None: a local process)
    job: str | None = None
    gpu: str | None = None

    def __str__(self) -> str:
        return (f"{self.host}:{self.pid}" + (f" {self.launcher} {self.job}" if self.launcher and self.job else "")
                + (f" gpu{self.gpu}" if self.gpu else ""))

    @classmethod
    def parse(cls, text: str | None) -> WorkerId | None:
        """The id a claims row holds (None: no worker, or not one this project wrote)."""
        parts = (text or "").split()
        host, _, pid = parts[0].rpartition(":") if parts else ("", "", "")
        if not host or not pid.isdigit():
            return None
        gpu = parts.pop()[3:] if len(parts) > 1 and parts[-1].startswith("gpu") else None
        launcher, job = (parts[1], parts[2]) if len(parts) == 3 else (None, None)
        return cls(host, int(pid), launcher, job, gpu)


def job_of(worker: str | None) -> str | None:
    """The launcher's job (Slurm: ``812_3``) of the worker that holds or held a claim, else None."""
    wid = WorkerId.parse(worker)
    return wid.job if wid else None


class ClaimLost(BronchoError):
    """This worker's claim was taken over by another worker (it had looked dead)."""


@dataclass
class WorkerStats:
    cells: int = 0
    finished: int = 0
    failed: int = 0
    lost: int = 0
    runner_s: float = 0.0
    outcomes: list[tuple[str, str]] = field(default_factory=list)  # (cell key, outcome)


class Worker:
    """The claim -> run -> record loop of one process."""

    def __init__(self, cfg: Config, cells: Sequence[Cell], store: SweepStore, runner: Runner = default_runner,
                 *, signals: StopSignals | None = None, sweep: str | None = None, ident: str | None = None,
                 exit_when_idle: bool = False):
        """``exit_when_idle``: return when nothing is claimable now (cells held by live workers elsewhere) instead
        of waiting for them; ``idle`` tells afterwards whether that is why the loop ended (Slurm tasks)."""
        self.cfg, self.store, self.runner = cfg, store, runner
        self.exit_when_idle, self.idle = exit_when_idle, False
        self.cells = {c.key: c for c in cells}
        self.sweep = sweep or cfg.name
        self.ident = ident or str(WorkerId(socket.gethostname(), os.getpid()))
        self.signals = signals or StopSignals()
        self.stats = WorkerStats()
        self._client = None
        self._parent: str | None = None
        self._unmarked: dict[str, tuple[str, str, tuple[str, ...], str | None]] = {}  # run -> how to end it
        self._damaged: set[str] = set()  # damaged rows said already

    @property
    def client(self):
        if self._client is None:
            self._client = client_for(self.cfg)
        return self._client

    def parent_run(self) -> str | None:
        """The sweep's parent run (found or created once per worker); None if the MLflow store refused."""
        if self._parent is None:
            try:
                exp = experiment_id(self.client, self.cfg)
                self._parent = sweep_parent(self.client, self.cfg, exp, self.sweep)
            except Exception as exc:  # noqa: BLE001 - nesting is cosmetic: a cell must run without it
                log.warning("no parent run for sweep %s: %s", self.sweep, exc)
                return None
        return self._parent

    def _db(self, fn: Callable[..., Any], *args: Any, **kw: Any) -> Any:
        """A storage call, retried through short outages (up to sweep.stale_after_s, while our claim holds)."""
        return retry(lambda: fn(*args, **kw), transient=lambda e: isinstance(e, StorageError),
                     what="claims storage unavailable", bound_s=self.cfg.sweep.stale_after_s, first_delay_s=0.2,
                     max_delay_s=5.0)

    # -- the loop ----------------------------------------------------------------
    def run(self) -> int:
        s = self.cfg.sweep
        future = FutureHeartbeats(s.stale_after_s)
        keys = self._usable(list(self.cells), future)
        self.parent_run()  # looked up once, before any claim: never while a claim waits for its heartbeat
        while not self.signals.stop:
            self.retry_unmarked()
            claim = self._db(self.store.claim, self.sweep, keys, self.ident, max_retries=s.max_retries,
                             stale_after_s=s.stale_after_s, overdue=future.overdue())
            if claim is None:
                keys = self._usable(keys, future)
                if self._db(self.store.all_done, self.sweep, keys, s.max_retries):
                    return EXIT_OK
                if self.exit_when_idle:  # no allocation held while other workers finish their cells
                    self.idle = True
                    return EXIT_OK
                self.signals.wait(s.poll_s)  # cells held by other workers: wait for them or their staleness
                continue
            if self._handle(claim) == "stop":
                return EXIT_INTERRUPTED
        return EXIT_INTERRUPTED

    def _usable(self, keys: list[str], future: FutureHeartbeats) -> list[str]:
        """``keys`` without the damaged rows (set aside, each said once: ``damage.py``); watches the claims whose
        heartbeat lies in the future (taken over once unchanged for stale_after_s of this worker's clock)."""
        rows = self._db(self.store.rows, self.sweep, keys)
        bad = {r.cell_key for r in damaged(rows)}
        for row in damaged(rows):
            if row.cell_key not in self._damaged:
                log.warning("%s", damage_line(row, self.store.redacted))
        self._damaged |= bad
        now = self._db(self.store.db_now)
        for row in future.new(rows, now):
            log.warning("%s", future_line(row, row.heartbeat - now, future.stale_after_s))
        return [k for k in keys if k not in bad]

    def _handle(self, claim: Claim) -> str:
        if claim.previous is not None:
            self._settle_orphans(claim.previous, keep=claim.released_run)
        cell = self.cells[claim.row.cell_key]
        done = self._finished_elsewhere(claim, cell)  # before anything else: a FINISHED run is never trained again
        if done is not None:
            self.stats.outcomes.append((cell.key, done))
            return done
        if claim.exhausted:
            prev = claim.previous
            reason = (f"worker {prev.worker} lost (no heartbeat for {self.cfg.sweep.stale_after_s:g} s) on the last "
                      f"allowed attempt ({prev.attempts}); reset with --retry-failed")
            self._db(self.store.fail, claim.token, reason, claim.released_run)
            self.stats.failed += 1
            return "failed"
        return self._run_claim(claim)

    def _finished_elsewhere(self, claim: Claim, cell: Cell) -> str | None:
        """A FINISHED MLflow run of the cell (MLflow is the record: the claims table may be new or behind) is
        recorded on the claim instead of training the cell again (``record.py``): a run finished by hand, or by a
        worker whose row never said so (killed between ending its run and writing the row, a row write that
        failed, a heartbeat that went stale or came from the future). The run is made this claim's first, so the
        worker that lost the claim leaves it FINISHED (``_terminate`` touches only its own claim's runs)."""
        try:
            run = finished_runs(self.cfg, [cell.key], self.sweep, self.client).get(cell.key)
            if run is not None:
                run_id = run.info.run_id
                if run.data.tags.get(TAG_CLAIM) not in (None, claim.token):
                    self.client.set_tag(run_id, TAG_CLAIM, claim.token)
                    if self.client.get_run(run_id).info.status != "FINISHED":  # its lost worker ended it meanwhile
                        return None
        except Exception as exc:  # noqa: BLE001 - cannot tell (a busy store too): the runner meets it and says so
            log.warning("could not look up a FINISHED run of %s in MLflow: %s", cell.label, exc)
            return None
        if run is None:
            return None
        if not self._db(self.store.finish, claim.token, run_id, duration_of(run) or 0.0):
            return self._lost(cell, None, claim.token)
        self.stats.finished += 1
        log.info("%s: already FINISHED in MLflow (run %s); recorded, not trained again", cell.label, run_id)
        return "finished"

    def _run_claim(self, claim: Claim) -> str:
        cell = self.cells[claim.row.cell_key]
        seen: dict[str, str] = {}

        def on_run_id(run_id: str) -> None:
            seen["run_id"] = run_id
            if not self._db(self.store.set_run_id, claim.token, run_id):
                raise ClaimLost(f"claim of cell {cell.label} was taken over before run {run_id} started")
            if run_id == claim.released_run:  # a resumed run is now made under this claim
                self.client.set_tag(run_id, TAG_CLAIM, claim.token)

        def on_lost() -> None:
            if self.signals.installed and self.signals.in_runner:  # stop our now-duplicate run at its next batch
                self.signals.self_term = True
                os.kill(os.getpid(), signal.SIGTERM)

        tags = {TAG_CLAIM: claim.token, TAG_WORKER: self.ident, TAG_ATTEMPT: str(claim.row.attempts)}
        if self._parent is not None:
            tags[TAG_PARENT] = self._parent
        hb = Heartbeat(self.store, claim.token, self.cfg.sweep.heartbeat_s, on_lost, self.signals,
                       lease_s=self.cfg.sweep.stale_after_s)
        try:
            resume = self._resumable(claim.released_run, cell)
        except (MlflowBusy, MlflowUnreachable) as exc:  # cannot tell whether to resume: never start afresh
            return self._release_busy(claim, cell, failure_reason(exc), None)
        kw = {"resume": resume} if resume else {}
        log.info("claimed %s (key %s, attempt %d)%s", cell.label, cell.key, claim.row.attempts,
                 f", resuming run {resume}" if resume else "")
        result, error = None, None
        t0 = time.perf_counter()
        hb.start()
        try:
            self.signals.in_runner = True
            result = self.runner(self.cfg, cell, extra_tags=tags, progress=False, run_id_callback=on_run_id,
                                 owns=hb.holds, **kw)
        except BaseException as exc:  # noqa: BLE001 - every outcome must be recorded on the row
            error = exc
        finally:
            self.signals.in_runner = False
            hb.halt()
            self.signals.self_term = False
        elapsed = time.perf_counter() - t0
        self.stats.cells += 1
        self.stats.runner_s += elapsed
        if result is not None:  # a signal that lands just after the runner returned: record the result first
            error = None  # (the stop request itself is kept in self.signals and ends the loop)
            if getattr(result, "stop_requested", None) and self.signals.requested is None:
                self.signals.requested = result.stop_requested  # arrived while the run was evaluating
        run_id = getattr(result, "run_id", None) or seen.get("run_id")
        try:
            outcome = self._record(claim, cell, result, error, run_id, elapsed, hb.lost)
        except StorageError as exc:  # the row is not written: a FINISHED run stays FINISHED, any other is ended
            if result is not None and result.status == "FINISHED" and run_id:
                raise StorageError(unrecorded_line(cell, run_id, exc)) from exc
            self._terminate(run_id, "KILLED", f"sweep worker {self.ident} could not record the outcome "
                            "(storage unreachable); the cell will be taken over", ("RUNNING",))
            raise
        self.stats.outcomes.append((cell.key, outcome))
        return outcome

    def _record(self, claim: Claim, cell: Cell, result: Any, error: BaseException | None, run_id: str | None,
                elapsed: float, lost: bool) -> str:
        if lost or isinstance(error, (ClaimLost, RunTakenOver)):
            return self._lost(cell, run_id, claim.token)
        if error is not None and is_interrupt(error):
            if self.signals.requested is None and getattr(error, "signal", None) is not None:
                self.signals.requested = error.signal  # run_cell's own handler caught it (SIGUSR1: requeue the task)
            self._terminate(run_id, "KILLED", f"sweep worker {self.ident} interrupted", ("RUNNING",))
            self._db(self.store.release, claim.token)
            log.info("interrupted %s: released (%s)", cell.label, failure_reason(error))
            return "stop"
        if isinstance(error, (MlflowBusy, MlflowUnreachable)):  # the store, not the cell: no attempt used
            return self._release_busy(claim, cell, failure_reason(error), run_id)
        if isinstance(error, WriteFailed):  # a full disk: FAILED, no attempt used, its checkpoint kept; the worker
            self._terminate(run_id, "FAILED", failure_reason(error), ("RUNNING",))  # stops (every cell meets it)
            self._db(self.store.fail, claim.token, failure_reason(error), run_id, elapsed, spent=False)
            error.recorded_on = cell.label  # the cell's row says it: the worker's exit is no crash (EXIT_RECORDED)
            raise error
        if error is not None:
            if not isinstance(error, (BronchoError, StorageError)):
                log.error("runner failed on %s", cell.label, exc_info=error)
            reason = failure_reason(error)
            self._terminate(run_id, "FAILED", reason, ("RUNNING",))
            return self._fail(claim, cell, reason, run_id, elapsed)
        if result.status == "FINISHED":
            duration = getattr(result, "duration_s", None) or elapsed
            if not self._db(self.store.finish, claim.token, result.run_id, duration):
                return self._lost(cell, run_id, claim.token)
            self.stats.finished += 1
            log.info("finished %s: run %s", cell.label, result.run_id)
            return "finished"
        reason = result.failure_reason or f"run ended {result.status}"
        return self._fail(claim, cell, reason, run_id, elapsed)

    def _fail(self, claim: Claim, cell: Cell, reason: str, run_id: str | None, elapsed: float) -> str:
        if not self._db(self.store.fail, claim.token, reason, run_id, elapsed):
            return self._lost(cell, run_id, claim.token)
        self.stats.failed += 1
        log.warning("failed %s: %s", cell.label, reason)
        if run_id and claim.row.attempts > self.cfg.sweep.max_retries:  # no retry will resume it: free the disk
            _remove_checkpoint(self.cfg, run_id, "failed on its last attempt")
        return "failed"

    def _release_busy(self, claim: Claim, cell: Cell, reason: str, run_id: str | None) -> str:
        """A run failed by a busy or unreachable MLflow store: the cell goes back (attempt not counted) with the
        reason and its checkpoint; its run is marked now if the store answers, else when it does (``_unmarked``),
        else by whoever claims the cell next (``_resumable``)."""
        self._terminate(run_id, "FAILED", reason, ("RUNNING",), token=claim.token, wait=False)
        self._db(self.store.release, claim.token, reason)
        self.stats.failed += 1
        log.warning("released %s (MLflow store busy or unreachable; attempt not counted, its checkpoint kept): %s",
                    cell.label, reason)
        self.signals.wait(self.cfg.sweep.poll_s)  # give the database a moment before claiming again
        return "released"

    def _lost(self, cell: Cell, run_id: str | None, token: str) -> str:
        self.stats.lost += 1
        log.warning("lost the claim of %s (no heartbeat for too long); its run %s is KILLED", cell.label, run_id)
        self._terminate(run_id, "KILLED", f"sweep worker {self.ident} lost its claim (no heartbeat for "
                        f"{self.cfg.sweep.stale_after_s:g} s); the cell was taken over", ("RUNNING", "FINISHED"),
                        token=token)
        return "lost"

    # -- MLflow side ---------------------------------------------------------------
    def _resumable(self, run_id: str | None, cell: Cell) -> str | None:
        """The cell's last run, resumed when its checkpoint is on this machine and it ended resumably.

        Resumable: KILLED (given back by Ctrl-C/SIGTERM), FAILED by the machine (disk full, busy
        database; ``errors.resumable``), or left RUNNING by a worker that released the cell without
        being able to close its run (the busy database again): that zombie is marked KILLED first.
        """
        if not run_id:
            return None
        has_checkpoint = resume_file(self.cfg, run_id).is_file()
        try:
            run = self.client.get_run(run_id)
            if run.data.tags.get(TAG_CELL_KEY) != cell.key:
                return None
            if run.info.status == "RUNNING":  # its cell was released, so no worker runs it any more
                self._terminate(run_id, "KILLED", f"left RUNNING by a worker that released the cell; "
                                f"{'resumed' if has_checkpoint else 'replaced'} by {self.ident}", ("RUNNING",))
                return run_id if has_checkpoint else None
        except (MlflowBusy, MlflowUnreachable):
            raise
        except Exception:  # noqa: BLE001 - deleted: start a fresh run
            return None
        if not has_checkpoint:
            return None
        reason = run.data.tags.get(TAG_FAILURE, "")
        ok = run.info.status == "KILLED" or (run.info.status == "FAILED" and resumable(reason))
        return run_id if ok else None

    def _terminate(self, run_id: str | None, status: str, reason: str, only: Sequence[str],
                   token: str | None = None, wait: bool = True) -> None:
        """Mark a run terminated unless it already ended otherwise (never leaves a second FINISHED run).

        ``token``: only while the run is still this claim's (a takeover may be resuming it under its own).
        ``wait=False``: the store is known to be away: try once (no busy wait); if that fails, it is tried
        again before each later claim of this worker (``retry_unmarked``)."""
        if not run_id:
            return
        client = self.client if wait else getattr(self.client, "raw", self.client)
        try:
            run = client.get_run(run_id)
            if token is not None and run.data.tags.get(TAG_CLAIM, token) != token:
                log.info("run %s is resumed under another claim now: left alone", run_id)
                return
            if run.info.status in only:
                client.set_tag(run_id, TAG_FAILURE, reason)
                client.set_terminated(run_id, status)
            self._unmarked.pop(run_id, None)
        except Exception as exc:  # noqa: BLE001 - the MLflow store is best effort here; logged
            if not wait:
                self._unmarked[run_id] = (status, reason, tuple(only), token)
            log.warning("could not mark run %s %s: %s", run_id, status,
                        str(exc).splitlines()[0][:300] if str(exc) else type(exc).__name__)

    def retry_unmarked(self) -> None:
        """Mark the runs an outage left RUNNING (``_terminate(wait=False)``) now that the store may be back."""
        for run_id, (status, reason, only, token) in list(self._unmarked.items()):
            self._terminate(run_id, status, reason, only, token=token, wait=False)

    def _settle_orphans(self, previous: CellRow, keep: str | None = None) -> None:
        """Kill the runs a lost worker left RUNNING for this cell (one it FINISHED without recording it on the row
        is the cell's result: ``_finished_elsewhere`` records it).

        The checkpoint of ``keep`` (the cell's run, which this claim resumes) stays: a takeover never deletes a
        resumable checkpoint. Only the checkpoints of other runs of the lost claim (none the cell will resume)
        are orphans."""
        run_ids = {previous.run_id} if previous.run_id else set()
        try:
            exp = experiment_id(self.client, self.cfg)
            found = search_runs(self.client, [exp], {TAG_CLAIM: previous.token or "-"})
            run_ids |= {r.info.run_id for r in found}
        except Exception as exc:  # noqa: BLE001
            log.warning("could not search the orphan runs of %s: %s", previous.label, exc)
        reason = (f"sweep worker {previous.worker} lost (no heartbeat for {self.cfg.sweep.stale_after_s:g} s); "
                  f"cell taken over by {self.ident}")
        for run_id in sorted(run_ids):
            self._terminate(run_id, "KILLED", reason, ("RUNNING", "SCHEDULED"))  # a FINISHED one: recorded (_handle)
            if run_id != keep:
                _remove_checkpoint(self.cfg, run_id, "orphaned by a lost worker")


def unrecorded_line(cell: Cell, run_id: str, exc: BaseException) -> str:
    """One line: a run FINISHED whose claims row could not be written; it stays FINISHED and is recorded later."""
    return (f"cell {cell.label}: run {run_id} FINISHED, but its claims row could not be written ({exc}); the run "
            "stays FINISHED and the next sweep records it for its cell (not trained again)")


def _remove_checkpoint(cfg: Config, run_id: str, why: str) -> None:
    """Free the disk of a checkpoint no cell will resume (a takeover starts afresh; a last failure is final)."""
    folder = checkpoint_dir(cfg, run_id)
    if folder.is_dir():
        remove_checkpoint(folder, f"run {run_id} {why}")  # only what provably is the run's checkpoint
