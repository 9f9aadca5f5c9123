"""One training run = one grid cell, tracked as one MLflow run from start to FINISHED/FAILED/KILLED.

``run_cell(cfg, cell)`` generates the dataset if it is missing, splits it for
the cell's population and fold, decodes frames into the cache, trains with
Lightning (early stopping on validation loss, best checkpoint kept), evaluates
the best weights on the test trajectories and logs params, tags, per-epoch and
test metrics and artifacts (resolved config, split manifest, predictions CSV,
trajectory plot, best checkpoint).

Faults: SIGINT (Ctrl-C) or SIGTERM stops training at the next batch, saves a
checkpoint and marks the run KILLED (``RunInterrupted`` is raised so callers
stop too); ``resume=`` continues such a run from its checkpoint. An ``on_epoch``
observer may raise ``RunPruned`` (the tuner's pruner): KILLED, tagged ``pruned``. A NaN/inf loss
or any other error marks the run FAILED with the reason in the
``failure_reason`` tag. Lightning writes checkpoints atomically (temp file +
rename through fsspec transactions).
"""

from __future__ import annotations

import logging
import signal
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

from .. import tracking
from ..config import Cell, Config
from ..errors import BronchoError
from .engine import RunInterrupted, RunPruned, RunStopped, prepare_data, train_and_evaluate

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    run_id: str
    status: str  # FINISHED, FAILED or KILLED
    metrics: dict[str, float] = field(default_factory=dict)
    failure_reason: str | None = None
    duration_s: float = 0.0
    train_time_s: float = 0.0
    stop_requested: int | None = None  # a SIGINT/SIGTERM that arrived during evaluation: the caller should stop


class _StopFlag:
    """Turns the first SIGINT/SIGTERM into a request to stop at the next batch; a second SIGINT aborts."""

    def __init__(self) -> None:
        self.signal: int | None = None

    def __call__(self, signum, frame) -> None:
        if self.signal is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signal = signum


@contextmanager
def _stop_on_signals(flag: _StopFlag) -> Iterator[None]:
    try:
        previous = {s: signal.signal(s, flag) for s in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _find_resumable(client, exp_id: str, cell: Cell) -> str:
    runs = tracking.search_runs(client, [exp_id], {tracking.TAG_CELL_KEY: cell.key}, ["KILLED", "FAILED", "RUNNING"])
    if not runs:
        raise BronchoError(f"--resume: no KILLED/FAILED run of cell {cell.label} (key {cell.key}) to resume")
    return runs[0].info.run_id


def _open_run(client, exp_id: str, cfg: Config, cell: Cell, resume: str | bool | None,
              extra_tags: dict[str, str]) -> tuple[str, bool]:
    """Create a new MLflow run for the cell, or reopen the one to resume; returns (run_id, resumed)."""
    if resume:
        run_id = resume if isinstance(resume, str) else _find_resumable(client, exp_id, cell)
        run = client.get_run(run_id)
        if run.data.tags.get(tracking.TAG_CELL_KEY) != cell.key:
            raise BronchoError(f"--resume {run_id}: that run belongs to another cell or config (key "
                               f"{run.data.tags.get(tracking.TAG_CELL_KEY)} != {cell.key})")
        client.update_run(run_id, "RUNNING")
        client.set_tag(run_id, tracking.TAG_FAILURE, "")
        return run_id, True
    run = client.create_run(exp_id, tags=tracking.cell_tags(cfg, cell, **extra_tags))
    return run.info.run_id, False


def _log_text(client, run_id: str, name: str, text: str, artifact_path: str | None = None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_text(text)
        client.log_artifact(run_id, str(path), artifact_path)


def run_cell(
    cfg: Config,
    cell: Cell,
    *,
    resume: str | bool | None = None,
    extra_tags: dict[str, str] | None = None,
    progress: bool = True,
    on_epoch: Callable[[int, dict[str, float]], None] | None = None,
    run_id_callback: Callable[[str], None] | None = None,
) -> RunResult:
    """Train and evaluate one cell; always leaves its MLflow run terminated (see the module doc)."""
    from ..data.generate import ensure_dataset

    t0 = time.perf_counter()
    client = tracking.client_for(cfg)
    exp_id = tracking.experiment_id(client, cfg)
    ensure_dataset(cfg)
    data = prepare_data(cfg, cell, progress=progress)  # validates frames before any run exists
    run_id, resumed = _open_run(client, exp_id, cfg, cell, resume, dict(extra_tags or {}))
    if run_id_callback:
        run_id_callback(run_id)
    flag = _StopFlag()
    try:
        if not resumed:
            client.set_tag(run_id, tracking.TAG_FINGERPRINT, data.fingerprint)
            tracking.log_params(client, run_id, tracking.flatten(cfg.dump()))
            _log_text(client, run_id, "config.yaml", tracking.redact_url(cfg.to_yaml()))
        with _stop_on_signals(flag):
            outcome = train_and_evaluate(cfg, cell, data, client, run_id, stop=flag, resumed=resumed,
                                         progress=progress, on_epoch=on_epoch)
    except RunStopped as exc:
        client.set_tag(run_id, tracking.TAG_FAILURE, str(exc))
        if isinstance(exc, RunPruned):
            client.set_tag(run_id, "pruned", "true")
        client.set_terminated(run_id, "KILLED")
        raise
    except KeyboardInterrupt:
        client.set_tag(run_id, tracking.TAG_FAILURE, "interrupted (second Ctrl-C)")
        client.set_terminated(run_id, "KILLED")
        raise RunInterrupted(f"run {run_id} interrupted; no checkpoint was saved at this point") from None
    except Exception as exc:  # noqa: BLE001 - any failure must terminate the run as FAILED
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        reason = f"{type(exc).__name__}: {reason}"[:4000]
        client.set_tag(run_id, tracking.TAG_FAILURE, reason)
        client.set_terminated(run_id, "FAILED")
        if not isinstance(exc, BronchoError):
            log.exception("run %s failed", run_id)
        return RunResult(run_id, "FAILED", failure_reason=reason, duration_s=time.perf_counter() - t0)
    client.set_terminated(run_id, "FINISHED")
    # A signal after training (during evaluation) let the run finish; it is passed on, not lost.
    return RunResult(run_id, "FINISHED", outcome.metrics, duration_s=time.perf_counter() - t0,
                     train_time_s=outcome.train_time_s, stop_requested=flag.signal)

