"""Fast fake cell runners for the sweep tests: each creates a real MLflow run (no training).

They have ``run_cell``'s signature and are importable by spawned worker
processes (the tests put this folder on ``sys.path``, which ``spawn`` passes on).
A command-line sweep runs them when given ``--runner sweep_fakes:fake_runner``
(``FAKE``), a documented option of ``bronchopose sweep``; a Slurm array task
gets it through its task spec.
Behaviour is driven by files in the directory named by ``$SWEEP_FAKE_DIR``:

- ``fail-<arch>`` containing N: the first N runs of each such cell end FAILED;
- ``block-<arch>``: the run writes ``started-<cell key>-<pid>`` and waits until
  ``release`` exists (a gate the test controls; interrupting it ends the run KILLED);
- ``full-<arch>``: the run meets a full disk (FAILED, its checkpoint kept, ``WriteFailed`` raised, as
  ``run_cell`` does);
- ``val-<arch>-<rot_loss>`` containing a number: the run's validation metric
  ``val_best.pos_l2``; its test metric ``pair.pos_l2.mean`` is ``10 - val``, so a
  selection that looked at test results would pick the worst (poisoned on purpose);
- every call leaves ``calls/<cell key>-<pid>-<n>`` behind.
"""

from __future__ import annotations

import os
import time
import uuid
from collections import Counter
from pathlib import Path

from bronchocli.errors import WriteFailed
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.contract import RunInterrupted, RunResult, resume_file
from bronchocli.runs.ownership import mark
from bronchocli.runs.views import reference_figures
from bronchocli.runs.records import TAG_CELL_KEY, TAG_FAILURE, TAG_KIND, TAG_SWEEP, cell_tags, log_metrics, search_runs

HERE = Path(__file__).resolve().parent
FAKE = ("--runner", "sweep_fakes:fake_runner")  # `bronchopose sweep` options that run the fake instead of training


def _dir() -> Path:
    return Path(os.environ["SWEEP_FAKE_DIR"])


def _metric(key: str) -> float:
    return int(key[:6], 16) / 2**24  # deterministic per cell, so status output can be checked


def calls(key: str) -> int:
    """How many times a fake runner was called for the cell."""
    return len(list((_dir() / "calls").glob(f"{key}-*")))


def fake_runner(cfg, cell, *, resume=None, extra_tags=None, progress=True, run_id_callback=None, **_):
    t0 = time.perf_counter()
    d = _dir()
    (d / "calls").mkdir(exist_ok=True)
    n_calls = len(list((d / "calls").glob(f"{cell.key}-*")))
    # The marker holds the storage URL the runner's config carries (tests check it has no password).
    (d / "calls" / f"{cell.key}-{os.getpid()}-{uuid.uuid4().hex[:6]}").write_text(cfg.storage.url)
    (d / f"gpu-{cell.key}").write_text(os.environ.get("CUDA_VISIBLE_DEVICES", "unset"))
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    if resume:  # like run_cell: reopen the KILLED run
        run_id = resume
        client.update_run(run_id, "RUNNING")
    else:
        run_id = client.create_run(exp, tags=cell_tags(cfg, cell, **(extra_tags or {}))).info.run_id
    if run_id_callback:
        run_id_callback(run_id)
    try:
        if (d / f"block-{cell.arch}").exists():
            (d / f"started-{cell.key}-{os.getpid()}").write_text(run_id)
            while not (d / "release").exists():
                time.sleep(0.02)
        if (d / f"full-{cell.arch}").exists():  # like run_cell on a full disk: FAILED, checkpoint kept, raised
            ckpt = resume_file(cfg, run_id)
            mark(ckpt.parent, run_id, cell.key)
            ckpt.write_text("fake checkpoint")
            error = WriteFailed(f"{ckpt.parent}: disk full (no space left on device; 0 B free); the run needs about "
                                "1.0 KB free to finish")
            client.set_tag(run_id, TAG_FAILURE, f"WriteFailed: {error}")
            client.set_terminated(run_id, "FAILED")
            raise error
        fail = d / f"fail-{cell.arch}"
        if fail.exists() and n_calls < int(fail.read_text() or 1):
            client.set_tag(run_id, TAG_FAILURE, "fake failure")
            client.set_terminated(run_id, "FAILED")
            return RunResult(run_id, "FAILED", failure_reason="fake failure", duration_s=time.perf_counter() - t0)
    except KeyboardInterrupt:  # like run_cell: a checkpoint, then KILLED
        ckpt = resume_file(cfg, run_id)
        mark(ckpt.parent, run_id, cell.key)  # as checkpoint.save does: the folder is provably the run's
        ckpt.write_text("fake checkpoint")
        client.set_terminated(run_id, "KILLED")
        raise RunInterrupted(f"run {run_id} interrupted") from None
    val_file = d / f"val-{cell.arch}-{cell.rot_loss}"
    if val_file.exists():
        val = float(val_file.read_text())
        metrics = {"val_best.pos_l2": val, "pair.pos_l2.mean": 10.0 - val, "acc.pos_l2.mean": 10.0 - val}
    else:
        metrics = {"pair.pos_l2.mean": _metric(cell.key), "acc.pos_l2.mean": 10 * _metric(cell.key),
                   "val_best.pos_l2": _metric(cell.key),
                   # the references' errors: pair 0.5 (training mean) and 1 (zero motion), accumulated 4 and 5, so
                   # the headline ratios and skills status shows are known (views.reference_figures, as training logs them)
                   "train_mean.pair.pos_l2.mean": 0.5, "zero_motion.pair.pos_l2.mean": 1.0,
                   "train_mean.acc.pos_l2.mean": 4.0, "zero_motion.acc.pos_l2.mean": 5.0}
        metrics |= reference_figures(metrics)
    log_metrics(client, run_id, metrics)
    client.set_terminated(run_id, "FINISHED")
    return RunResult(run_id, "FINISHED", metrics, duration_s=time.perf_counter() - t0)


def runs_by_cell(cfg, status: str | None = "FINISHED") -> Counter:
    """How many MLflow runs of each cell key have ``status`` (None: any)."""

    client = client_for(cfg)
    exp = client.get_experiment_by_name(cfg.experiment_name)
    if exp is None:
        return Counter()
    runs = search_runs(client, [exp.experiment_id], {TAG_SWEEP: cfg.name, TAG_KIND: "cell"},
                                [status] if status else None)
    return Counter(r.data.tags[TAG_CELL_KEY] for r in runs)


def wait_for(predicate, what: str, procs=(), limit: float = 120.0):
    """Wait for an event the test controls (a file, a state); the limit only guards against hanging."""
    end = time.monotonic() + limit
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"gave up waiting for {what}")
        if procs and not any(p.is_alive() for p in procs):
            raise AssertionError(f"workers exited while waiting for {what}")
        time.sleep(0.05)


def idle_worker(log_path: str, stop_event) -> None:
    """A local worker process that writes its log and waits for a signal (``LocalProcesses``' target in tests of
    who a cancel reaches)."""
    import signal

    Path(log_path).write_text("idle worker\n")
    while True:
        signal.pause()
