"""Sweeps: a grid of cells run exactly once each by cooperating workers over shared SQL storage.

- ``storage``: the claims table (SQLite on one machine, PostgreSQL for many) and its atomic transitions;
- ``worker``: the claim -> run -> record loop with its heartbeat and signal handling; the cell runner;
- ``plan``: the stages and their cells, ``StageWalk`` (the one walk through the stages every launcher uses),
  the claims rows and the shared state prepared once before workers start;
- ``selection``: a selecting stage's ranking by a validation metric, recorded once and logged to MLflow;
- ``pool``: local worker processes and the parent's live view;
- ``staged``: the local launcher (stages in order, each with the worker pool) and one worker's walk;
- ``slurm``: the Slurm driver (sbatch, squeue, scancel, scontrol, the batch script) and the launcher's watch;
- ``task``: a Slurm array task's entry point (``python -m bronchocli.sweep.task <spec>``);
- ``entry``: ``bronchopose sweep``'s modes as library calls (run, dry_run, gc, launch_slurm, cancel);
- ``record``: MLflow as the record of what finished (claims rows rebuilt from FINISHED runs, the check before
  training, the read-only view for ``--dry-run`` and ``status``);
- ``placement``, ``housekeeping``: GPUs for local workers; checkpoints on disk (inventory, --gc, --repair; what
  is provably a checkpoint is ``runs.ownership``'s call);
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
