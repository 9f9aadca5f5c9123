"""What the sweep and the training engine agree on about a run, without importing torch.

Where a run's checkpoints live, how many CPU threads it gets, what a run
returns, and the exceptions that stop a run early (a sweep worker catches
them by type).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from . import urls
from .config import Config
from .errors import BronchoError

RESUME_FILE = "last.pt"  # full training state of an unfinished run (removed when the run FINISHED)
BEST_FILE = "best.pt"  # weights of the best validation so far
REJECTED_SUFFIX = ".rejected"  # a checkpoint refused on resume is renamed last.pt.rejected (kept, never loaded)
GPU_SHARE_ENV = "BRONCHOPOSE_GPU_SHARE"  # sweep workers pinned to this process's GPU, itself included


def gpu_share(env: dict[str, str] | None = None) -> int:
    """How many processes share this process's GPU (``sweep --per-gpu K`` sets K; 1 when unset or bad)."""
    value = (os.environ if env is None else env).get(GPU_SHARE_ENV, "1")
    return int(value) if value.isdigit() and int(value) > 0 else 1


@dataclass
class RunResult:
    """What a cell runner (``training.run.run_cell`` or a test/benchmark stand-in) returns to the sweep."""

    run_id: str
    status: str  # FINISHED, FAILED or KILLED
    metrics: dict[str, float] = field(default_factory=dict)
    failure_reason: str | None = None
    duration_s: float = 0.0
    train_time_s: float = 0.0
    stop_requested: int | None = None  # a SIGINT/SIGTERM that arrived during evaluation: the caller should stop


class RunStopped(BronchoError):
    """Training stopped on purpose before the end; the MLflow run is marked KILLED with the reason."""


class RunInterrupted(RunStopped):
    """Training was stopped by SIGINT/SIGTERM; the run is KILLED and can be resumed."""

    exit_code = 130


class RunPruned(RunStopped):
    """An observer (the Optuna pruner) stopped the run after a validation; KILLED, tagged ``pruned``."""


def failure_reason(exc: BaseException) -> str:
    """``Type: first line of the message``: the ``failure_reason`` of a run and a sweep cell (one line, bounded)."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else type(exc).__name__}"[:4000]


def checkpoint_dir(cfg: Config, run_id: str) -> Path:
    return cfg.paths.checkpoints / run_id


def resume_file(cfg: Config, run_id: str) -> Path:
    return checkpoint_dir(cfg, run_id) / RESUME_FILE


def cpu_threads(cfg: Config, workers: int = 1) -> int:
    """torch CPU threads of one run: ``train.threads``, else the cores shared by ``workers`` runs."""
    return cfg.train.threads or max(1, (os.cpu_count() or 1) // max(1, workers))


def process_age_s() -> float | None:
    """Seconds since this process started (Linux ``/proc``; None elsewhere): the start-up a user waits through."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        start_ticks = int(fields[19])  # field 22 of stat(5), counted after the command name
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


# -- path pre-flight: one line before anything is created -----------------------------------------------------


def _why_not_writable(folder: Path) -> str | None:
    """Why nothing can be created in the existing folder ``folder`` (None: it can)."""
    try:
        if os.statvfs(folder).f_flag & os.ST_RDONLY:
            return "read-only file system"
    except OSError as exc:
        return exc.strerror or str(exc)
    if not os.access(folder, os.W_OK | os.X_OK):
        return "permission denied"
    return None


def check_output(path: Path, setting: str, kind: str = "folder") -> None:
    """``path`` (a folder, or a ``file`` to create) can be written: BronchoError naming the setting otherwise.

    Creates nothing: the nearest existing ancestor must be a folder this user may write in, on a writable
    file system, and ``path`` itself, if it exists, must be of the right kind (and writable).
    """
    if path.exists():
        if kind == "folder" and not path.is_dir():
            raise BronchoError(f"{setting} {path}: is a file, not a folder; point {setting} at a folder")
        if kind == "file" and path.is_dir():
            raise BronchoError(f"{setting} {path}: is a folder, not a database file; point {setting} at a file")
        target = path if path.is_dir() else path.parent
        why = _why_not_writable(target)
        if why is not None:
            raise BronchoError(f"{setting} {path}: cannot write there ({why}); point {setting} at a writable place")
        return
    nearest = path.parent
    while not nearest.exists() and nearest != nearest.parent:
        nearest = nearest.parent
    if not nearest.is_dir():
        raise BronchoError(f"{setting} {path}: {nearest} is a file, so no {kind} can be created there")
    why = _why_not_writable(nearest)
    if why is not None:
        raise BronchoError(f"{setting} {path}: cannot create it in {nearest} ({why}); point {setting} at a "
                           "writable place")


def check_dataset_root(cfg: Config) -> None:
    """``dataset.root`` is a folder (or missing, to be generated): a file there is one line, before anything runs."""
    root = cfg.paths.dataset
    if root.exists() and not root.is_dir():
        raise BronchoError(f"dataset.root {root}: is a file, not a dataset folder; point dataset.root at the "
                           "folder holding dataset.json (or at a new folder to generate one there)")
    if not root.exists():
        check_output(root, "dataset.root")


def check_paths(cfg: Config, *, storage: bool = False, logs: bool = False) -> None:
    """Every folder and database file a training command writes, checked before any is created (one line each).

    ``storage``: also the SQLite file of ``storage.url`` (sweep, tune); ``logs``: the sweep's worker logs.
    """
    check_dataset_root(cfg)
    outputs = [(cfg.paths.checkpoints, "tracking.checkpoints", "folder"), (cfg.paths.cache, "data.cache_dir", "folder")]
    tracking_db = urls.sqlite_file(cfg.paths.tracking_uri)
    if tracking_db is not None:
        outputs += [(tracking_db, "tracking.uri", "file"), (cfg.paths.artifacts, "tracking.artifacts", "folder")]
    elif not urls.is_server(cfg.paths.tracking_uri) and not urls.is_postgres(cfg.paths.tracking_uri):
        outputs.append((cfg.paths.artifacts, "tracking.artifacts", "folder"))
    storage_db = urls.sqlite_file(cfg.paths.storage_url)
    if logs:
        outputs.append((cfg.paths.sweep_logs, "sweep.logs", "folder"))
    if storage_db is not None and storage:
        outputs.append((storage_db, "storage.url", "file"))
    for path, setting, kind in outputs:
        check_output(path, setting, kind)
