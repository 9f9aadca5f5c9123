"""Sweeps: a grid of cells run exactly once each by cooperating workers over shared SQL storage.

- ``storage``: the claims table (SQLite on one machine, PostgreSQL for many) and its atomic transitions;
- ``worker``: the claim -> run -> record loop with its heartbeat and signal handling; ``WorkerId``;
- ``liveness``: the heartbeat and the stop signals; heartbeats from the future judged on the reader's clock;
- ``damage``: claims rows this code cannot use, set aside with one line each, and ``status --repair`` of them;
- ``plan``: the stages and their cells, ``StageWalk`` (the one walk through the stages every launcher uses),
  the claims rows and the shared state prepared once before workers start;
- ``selection``: a selecting stage's ranking by a validation metric, recorded once and logged to MLflow;
- ``launchers``: where workers run, one protocol (``launchers.base.Launcher``) and its implementations, each in
  its own module: ``local`` (child processes here), ``slurm`` (job arrays); a registry of their names;
- ``stagework``: the one worker entry every launcher starts (``worker_main``: one worker through the stages);
- ``task``: a detached worker's command (``python -m bronchocli.sweep.task <spec>``) and its spec;
- ``launch``: ``sweep run`` with any launcher, the one driver (submit what is missing, watch, next stage, top up);
- ``planview``: the plan as the commands print it (``sweep plan``, and ``sweep run`` before it submits);
- ``entry``: the sweep's verbs as library calls (run, dry_run, gc, cancel), ``status``, ``tune``;
- ``record``: MLflow as the record of what finished (claims rows rebuilt from FINISHED runs, rows whose run was
  deleted by hand made pending, the check before training, the read-only view for ``sweep plan`` and ``status``);
- ``placement``, ``housekeeping``: GPUs for local workers; checkpoints on disk (inventory, ``sweep gc``,
  ``--repair``; what is provably a checkpoint is ``runs.ownership``'s call);
- ``order``: the claim order; ``status``, ``summary``: tables for the plan, the live view, ``bronchopose status``
  and the parent runs;
- ``tuning``: ``bronchopose tune``'s Optuna studies on the same storage, their trials rows of the claims table
  claimed by sweep workers of any launcher through the one driver (its own modules: ``tuning/__init__.py``).

See docs/sweep.md for the model and the exactly-once argument.
"""

import importlib
from typing import Any

# The package's names, each from its module, imported when first asked for (PEP 562): importing one module of the
# package (``sweep.launchers`` for the command line's launcher flags) does not load the others (MLflow, SQLAlchemy).
_FROM = {
    "Launcher": "launchers",
    **dict.fromkeys(("Plan", "plan_cells", "prepare", "read_plan"), "plan"),
    **dict.fromkeys(("WorkerJob", "worker_config", "worker_main"), "stagework"),
    **dict.fromkeys(("FAILED", "FINISHED", "PENDING", "RUNNING", "TAG_CLAIM", "CellRow", "Claim", "StorageError",
                     "SweepStore"), "storage"),
    **dict.fromkeys(("TAG_ATTEMPT", "TAG_WORKER", "StopSignals", "Worker", "WorkerId"), "worker"),
}


def __getattr__(name: str) -> Any:
    if name in _FROM:
        return getattr(importlib.import_module(f".{_FROM[name]}", __name__), name)
    try:  # a submodule asked for as an attribute (``from bronchocli.sweep import entry`` imports it itself)
        return importlib.import_module(f".{name}", __name__)
    except ModuleNotFoundError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None

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
    "Launcher",
    "Plan",
    "StopSignals",
    "StorageError",
    "SweepStore",
    "Worker",
    "WorkerId",
    "WorkerJob",
    "plan_cells",
    "prepare",
    "read_plan",
    "worker_config",
    "worker_main",
]
