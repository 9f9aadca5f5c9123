"""Sweeps: a grid of cells run exactly once each by cooperating workers over shared SQL storage.

- ``storage``: the claims table (SQLite on one machine, PostgreSQL for many) and its atomic transitions;
- ``worker``: the claim -> run -> record loop with its heartbeat and signal handling;
- ``plan``: the stages, their cells and selections, and the shared state prepared once before workers start;
- ``staged``: ``bronchopose sweep`` as a library call (stages in order, each with the worker pool);
- ``pool``: local worker processes and the parent's live view;
- ``status``: tables for the plan, the live view and ``bronchopose status``;
- ``tuning``: Optuna studies on the same storage, one MLflow run per trial.

See docs/sweep.md for the model and the exactly-once argument.
"""

from .plan import Plan, plan_cells, prepare, read_plan
from .pool import PoolResult, run_pool, spawn_worker, worker_config
from .storage import FAILED, FINISHED, PENDING, RUNNING, TAG_CLAIM, CellRow, Claim, StorageError, SweepStore
from .worker import TAG_ATTEMPT, TAG_WORKER, StopSignals, Worker, WorkerSpec, worker_process

__all__ = [
    "FAILED",
    "FINISHED",
    "PENDING",
    "RUNNING",
    "TAG_ATTEMPT",
    "TAG_CLAIM",
    "TAG_WORKER",
    "CellRow",
    "Claim",
    "Plan",
    "PoolResult",
    "StopSignals",
    "StorageError",
    "SweepStore",
    "Worker",
    "WorkerSpec",
    "plan_cells",
    "prepare",
    "read_plan",
    "run_pool",
    "spawn_worker",
    "worker_config",
    "worker_process",
]
