"""One training run = one cell, tracked as one MLflow run from start to FINISHED/FAILED/KILLED.

``run_cell(cfg, cell)`` prepares the data (split, frame cache, statistics; a
bad frame fails before any MLflow run exists), opens the run, trains and
evaluates (``engine``), logs everything (``artifacts``) and terminates the
run. The dataset must exist: ``bronchopose train``/``sweep``/``tune``
generate it first, as an explicit step of their start-up.

Faults: SIGINT (Ctrl-C), SIGTERM (scancel, ``scontrol requeue``,
preemption), SIGHUP (the terminal closed) or the warning signal of the launcher whose worker runs it
(``interrupts.warned_by``: Slurm's SIGUSR1 before its time limit) stops training after the
current optimiser step, saves a resumable checkpoint of that step and marks
the run KILLED with the signal and the checkpoint's path as its reason
(``RunInterrupted``, carrying the signal, is raised so callers stop too);
``resume=`` continues such a run from its checkpoint. Between signals a
checkpoint is written every ``train.checkpoint_every_s`` seconds, so a hard
kill (OOM, ``kill -9``) loses at most that much. An ``on_validation`` observer may raise
``RunPruned`` (the tuner's pruner): KILLED, tagged ``pruned``. With ``owns`` (a sweep worker's claim,
asked before every checkpoint and before the run is ended) a process that lost its run to another worker
stops writing to it (``RunTakenOver``: no checkpoint, no status; the run is the new owner's). A NaN/inf loss
or any other error marks the run FAILED with the reason in the
``failure_reason`` tag. A signal that arrives during the test evaluation lets
the run finish; ``RunResult.stop_requested`` passes it on.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from .. import interrupts, runkeys
from ..cells import Cell
from ..config import Config
from ..errors import BronchoError, MlflowUnreachable, OutOfMemory, out_of_memory, resumable
from ..models import initialisation
from ..runs import cores
from ..runs.client import MetricBuffer, MlflowBusy, check_reachable, client_for, experiment_id, redacted_uri
from ..runs.contract import (
    REJECTED_SUFFIX,
    RunInterrupted,
    RunPruned,
    RunResult,
    RunStopped,
    RunTakenOver,
    checkpoint_dir,
    failure_reason,
    resume_file,
)
from ..runs.ownership import remove_checkpoint
from ..runs.processes import fail_pending_models, process_alive, process_tags, repair_zombie
from ..runs.records import TAG_CELL_KEY, TAG_FAILURE, TAG_INIT, cell_tags, search_runs
from ..runs.system import system_metrics
from . import artifacts, checkpoint
from .resumable import differences, find_resumable
from .device import device_for, env_tags, speed_for
from .engine import fit_and_evaluate
from .prepare import prepare

log = logging.getLogger(__name__)


class StopFlag:
    """Turns the first stop signal into a request to stop after the current step; a second SIGINT aborts.

    ``owns`` (from a sweep worker) says whether this process still owns the run; the training loop asks it
    before each checkpoint it writes (``RunTakenOver`` when not), so a worker that stalled and lost its cell
    never overwrites the checkpoint of the worker that took the run over."""

    def __init__(self, owns: Callable[[], bool] | None = None) -> None:
        self.signal: int | None = None
        self.owns = owns

    def __call__(self, signum, frame) -> None:
        if self.signal is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        interrupts.note(signum)  # `train`'s exit code names it (143 for SIGTERM)
        self.signal = signum


@contextmanager
def _stop_on_signals(flag: StopFlag) -> Iterator[None]:
    try:
        previous = {s: signal.signal(s, flag) for s in interrupts.stop_signals()}
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _open_run(client, exp_id: str, cfg: Config, cell: Cell, resume: str | bool | None,
              extra_tags: dict[str, str]) -> tuple[str, dict[str, Any] | None]:
    """Create a new MLflow run for the cell, or reopen the one to resume; returns (run_id, its saved state)."""
    if not resume:
        for zombie in search_runs(client, [exp_id], {TAG_CELL_KEY: cell.key}, ["RUNNING"]):
            if process_alive(zombie.data.tags) is False:  # this cell's earlier run, its process died
                repair_zombie(client, zombie, "a new run of its cell")
        run = client.create_run(exp_id, tags=cell_tags(cfg, cell, **extra_tags, **process_tags()))
        return run.info.run_id, None
    run_id = resume if isinstance(resume, str) else find_resumable(cfg, client, exp_id, cell)
    try:
        run = client.get_run(run_id)
    except Exception:  # noqa: BLE001 - MLflow raises its own exception types for a missing run
        raise BronchoError(f"--run-id {run_id}: no such MLflow run in {redacted_uri(cfg)}") from None
    if run.data.tags.get(TAG_CELL_KEY) != cell.key:
        theirs = {k: run.data.tags.get(k) or "" for k in cell.tags()}
        what = (f"made with other settings: {differences(cfg, client, run_id)}" if theirs == cell.tags() else
                "of another cell: " + ", ".join(f"{k} {v or '(unset)'} (now {cell.tags()[k] or '(unset)'})"
                                                 for k, v in theirs.items() if v != cell.tags()[k]))
        raise BronchoError(f"--resume {run_id}: that run (key {run.data.tags.get(TAG_CELL_KEY)}, this cell's is "
                           f"{cell.key}) was {what}; resume it with the flags and settings it was made with")
    repaired = repair_zombie(client, run, "train --resume")
    path = resume_file(cfg, run_id)
    if not path.is_file():
        raise BronchoError(f"--resume {run_id}: no checkpoint at {path} (it is kept on the machine that ran it)")
    try:
        state = checkpoint.load(path, run_id=run_id, cell_key=cell.key)
    except checkpoint.BadCheckpoint as exc:  # never loaded: set aside (kept for inspection) and fail the run
        rejected = path.with_name(path.name + REJECTED_SUFFIX)
        path.replace(rejected)
        exc = checkpoint.BadCheckpoint(f"{exc}; moved to {rejected.name}, the next run of the cell starts afresh")
        _end_run(client, run_id, "FAILED", failure_reason(exc))
        raise exc from None
    client.update_run(run_id, "RUNNING")
    if repaired or TAG_FAILURE in run.data.tags:
        client.delete_tag(run_id, TAG_FAILURE)  # a resumed run has no failure (and no empty tag)
    for key, value in {**extra_tags, **process_tags()}.items():  # the worker, claim, attempt resuming it now
        client.set_tag(run_id, key, value)
    log.info("resuming run %s from its checkpoint of step %d (%s)", run_id, state["step"], path)
    client.log_metric(run_id, runkeys.RESUMED_FROM_STEP, float(state["step"]), step=int(state["step"]))
    return run_id, state


class _StepBar:
    """A rich progress bar over optimiser steps (nothing when ``show`` is False)."""

    def __init__(self, show: bool, label: str) -> None:
        self.bar = Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TextColumn("steps"),
                            TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn(),
                            transient=False) if show else None
        self.task = None
        self.best = float("inf")

    def step(self, step: int, total: int) -> None:
        if self.bar is None:
            return
        if self.task is None:
            self.bar.start()
            self.task = self.bar.add_task("train", total=total, completed=step, info="")
        self.bar.update(self.task, completed=step)

    def validated(self, step: int, values: dict[str, float]) -> None:
        self.best = min(self.best, values[runkeys.VAL_LOSS])
        if self.bar is not None and self.task is not None:
            self.bar.update(self.task, info=f"val_loss {values[runkeys.VAL_LOSS]:.4g} (best {self.best:.4g})")

    def phase(self, label: str, text: str) -> None:
        """What the run does after its last step (test evaluation, logging): in the bar, else in the log."""
        if self.bar is not None and self.task is not None:
            self.bar.update(self.task, info=text + " ...")
        else:
            log.info("%s: %s ...", label, text)

    def close(self) -> None:
        if self.bar is not None and self.task is not None:
            self.bar.stop()


def run_cell(
    cfg: Config,
    cell: Cell,
    *,
    resume: str | bool | None = None,
    extra_tags: dict[str, str] | None = None,
    progress: bool = True,
    on_validation: Callable[[int, dict[str, float]], None] | None = None,
    run_id_callback: Callable[[str], None] | None = None,
    owns: Callable[[], bool] | None = None,
    reachable: bool = False,
) -> RunResult:
    """Train and evaluate one cell; always leaves its MLflow run terminated (see the module doc), unless ``owns``
    says another worker took it over. ``reachable``: the caller has just checked that the MLflow store answers
    (``train``'s entry does, before it looks for the cell's runs); otherwise it is checked here, before any work. From its start the process holds a claim on its share of the CPU cores
    (``runs.cores``), decided when training starts, at each validation and every few seconds of training."""
    with cores.for_run(cfg) as share:
        return _run_cell(cfg, cell, resume=resume, extra_tags=extra_tags, progress=progress,
                         on_validation=on_validation, run_id_callback=run_id_callback, owns=owns, share=share,
                         reachable=reachable)


def _run_cell(cfg: Config, cell: Cell, *, resume: str | bool | None, extra_tags: dict[str, str] | None,
              progress: bool, on_validation: Callable[[int, dict[str, float]], None] | None,
              run_id_callback: Callable[[str], None] | None, owns: Callable[[], bool] | None,
              share: cores.CoreShare, reachable: bool) -> RunResult:
    t0 = time.perf_counter()
    device = device_for(cfg)  # an explicit device this machine lacks: one line, before any work or MLflow run
    fast = speed_for(cfg, cell.arch, device)  # a bad train.speed_settings file: one line, before any work
    if not reachable:
        check_reachable(cfg)  # a dead server fails within runs.timeout_s, before any work
    tags = dict(extra_tags or {})
    if not resume:  # missing/unreachable backbone weights fail before any work; the run records its initialisation
        tags[TAG_INIT] = initialisation(cfg.paths.pretrained, [cell.arch], cfg.model.backbone)[cell.arch]
    data = prepare(cfg, cell, progress=progress)  # a bad dataset fails here, before any MLflow store or run
    client = client_for(cfg)
    exp_id = experiment_id(client, cfg)
    run_id, state = _open_run(client, exp_id, cfg, cell, resume, tags)
    for key, value in env_tags(cfg, device, cell.arch).items():  # on a resume too: the device may have changed
        client.set_tag(run_id, key, value)
    if run_id_callback:
        run_id_callback(run_id)
    flag = StopFlag(owns)

    def still_ours() -> bool:
        return owns is None or owns()
    bar = _StepBar(progress, cell.label)
    metrics_out = MetricBuffer(client, run_id)  # an MLflow outage during training is waited out, not fatal
    if state is not None:  # validations the checkpoint holds but MLflow lacks (buffered when the store went away)
        logged = {m.step for m in client.get_metric_history(run_id, runkeys.VAL_LOSS)}
        for h in state["history"]:
            if int(h["step"]) not in logged:
                metrics_out.log({k: v for k, v in h.items() if k != "step"}, int(h["step"]))

    def validated(step: int, values: dict[str, float]) -> None:
        metrics_out.log({**values, runkeys.THREADS: float(share.check().threads)}, step)  # at step = optimiser step
        bar.validated(step, values)
        if on_validation is not None:
            on_validation(step, values)

    ckpt = checkpoint_dir(cfg, run_id)
    checkpoint.reserve(checkpoint.store_folders(cfg))  # room to end the run if the disk fills (the failure path)
    threads = share.check()  # as late as possible: processes started at the same time have all claimed by now
    try:
        if state is None:  # the speed setting it trains with (measured per architecture and device, or the config's)
            artifacts.log_start(client, run_id, cfg, data, cell, {**fast.params(), **threads.params()})
        with _stop_on_signals(flag), system_metrics(cfg, run_id, resume=state is not None):
            try:
                outcome = fit_and_evaluate(cfg, cell, data, ckpt_dir=ckpt, resume_state=state, stop=flag,
                                           on_validation=validated, on_step=bar.step,
                                           on_phase=lambda text: bar.phase(cell.label, text),
                                           on_curves=metrics_out.log_points,  # buffered like validations
                                           threads=share.fresh)
                if not still_ours():  # stalled past the cut-off while evaluating: the outcome is the new owner's
                    raise RunTakenOver(f"run {run_id} was taken over by another sweep worker; its outcome is not "
                                       "logged by this one")
                bar.phase(cell.label, "logging metrics, predictions" +
                          ("" if cfg.runs.model_artifact == "none" else " and the MLflow Model"))
                metrics_out.flush(wait=True)  # the store must be back (within runs.busy_timeout_s) to finish
                artifacts.log_outcome(client, run_id, cfg, cell, data, outcome)
            finally:
                bar.close()
            client.set_terminated(run_id, "FINISHED")  # before the checkpoint goes: an outage here resumes it
    except RunTakenOver as exc:
        log.warning("%s", exc)  # nothing written: the run, its status and its checkpoint are the new owner's
        raise
    except RunStopped as exc:
        exc.run_id = run_id  # `train` names the run and the call that resumes it (resumable.advised)
        if isinstance(exc, RunPruned):
            client.set_tag(run_id, "pruned", "true")
            remove_checkpoint(ckpt, "pruned trial")  # a pruned trial is never resumed
        _end_run(client, run_id, "KILLED", str(exc))
        raise
    except KeyboardInterrupt:
        if still_ours():
            _end_run(client, run_id, "KILLED", "interrupted (second Ctrl-C)")
        stopped = RunInterrupted(f"run {run_id} interrupted; no checkpoint was saved at this point")
        stopped.run_id = run_id
        raise stopped from None
    except Exception as exc:  # noqa: BLE001 - any failure must terminate the run as FAILED
        full = checkpoint.as_write_failure(exc, checkpoint.run_needs(ckpt), checkpoint.failure_folder(cfg))
        if full is not None:  # a full disk anywhere under the run: one line (the folder, the space), resumable;
            checkpoint.release_reserve(checkpoint.store_folders(cfg))  # the room to end the run FAILED
            exc = full
        exc = out_of_memory(exc) or exc  # MemoryError, torch's allocator: one line, the run FAILED with it
        reason = failure_reason(exc)
        if not still_ours():  # a stalled process failing after the takeover: the run is the new owner's
            log.warning("run %s failed here (%s) after another sweep worker took it over; left to that one",
                        run_id, reason)
            raise RunTakenOver(f"run {run_id} was taken over by another sweep worker ({reason})") from None
        _end_run(getattr(client, "raw", client) if isinstance(exc, OUTAGES) else client, run_id, "FAILED", reason)
        if not isinstance(exc, OUTAGES):  # a model whose upload failed (a full disk) is not left PENDING on the run
            _fail_pending_models(client, run_id)
        if not resumable(exc):  # only a failure of the machine (errors.py) is worth resuming
            remove_checkpoint(ckpt, "run failed, not resumable")
        if isinstance(exc, RAISE_AFTER_FAILED):  # one line and exit 2 for `train`; the sweep releases/fails the cell
            exc.run_id = run_id  # `train` says how to resume it (resumable.advised)
            raise exc from None
        if not isinstance(exc, BronchoError):
            log.exception("run %s failed", run_id)
        return RunResult(run_id, "FAILED", failure_reason=reason, duration_s=time.perf_counter() - t0)
    remove_checkpoint(ckpt, "run finished")  # resumable state is only needed while the run is unfinished
    before = sum(float(t) for t in state["times"]) if state is not None else 0.0  # the cell's time before a resume
    return RunResult(run_id, "FINISHED", outcome.metrics, duration_s=time.perf_counter() - t0 + before,
                     train_time_s=outcome.fit.train_time_s, stop_requested=flag.signal)


# Raised on (after the run is FAILED) so `train` prints one line and exits 2 and a sweep worker can tell them apart.
RAISE_AFTER_FAILED = (checkpoint.WriteFailed, checkpoint.BadCheckpoint, MlflowBusy, MlflowUnreachable, OutOfMemory)
OUTAGES = (MlflowBusy, MlflowUnreachable)  # the store is away: marking the run is tried once, not waited for



def _fail_pending_models(client, run_id: str) -> None:
    """Mark FAILED the run's logged models left PENDING by the failure (best effort, like ``_end_run``)."""
    try:
        fail_pending_models(client, client.get_run(run_id))
    except Exception as exc:  # noqa: BLE001 - logged; the caller reports the original failure
        log.warning("could not mark the logged models of run %s (%s)", run_id,
                    str(exc).splitlines()[0] if str(exc) else type(exc).__name__)


def _end_run(client, run_id: str, status: str, reason: str) -> None:
    """Terminate the run with its reason, best effort: a store that is busy or full must not hide the reason.

    A run this cannot end stays RUNNING with its process tags; whoever touches it next (``train --resume``,
    the sweep's takeover, ``status --repair``) finds its process gone and ends it (``runs.processes.repair_zombie``).
    """
    try:
        client.set_tag(run_id, TAG_FAILURE, reason)
        client.set_terminated(run_id, status)
    except Exception as exc:  # noqa: BLE001 - logged; the caller reports the original failure
        log.warning("could not mark run %s %s (%s); it will be repaired when next touched", run_id, status,
                    str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
