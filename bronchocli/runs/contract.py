"""The run contract: what the sweep and the training engine agree on about a run, without importing torch.

Where a run's checkpoints live, how many processes share its GPU, what a run returns, and the exceptions that
stop a run early (a sweep worker catches them by type). How many CPU threads it takes is ``cores``'s.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..config import Config
from ..errors import BronchoError

RESUME_FILE = "last.pt"  # full training state of an unfinished run (removed when the run FINISHED)
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
    """Training was stopped by a signal (SIGINT, SIGTERM, SIGUSR1); the run is KILLED and can be resumed."""

    exit_code = 130
    signal: int | None = None  # the signal that stopped it: a sweep worker stops (and a Slurm task requeues) on it


class RunTakenOver(RunStopped):
    """This process no longer owns its run: it stalled past the sweep's staleness cut-off and another worker took
    the cell over (resuming the same run from the same checkpoint). Nothing more of this process is written to
    the run or its checkpoint; the run is left to its new owner."""


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
