"""Which checkpoints are still needed, what they cost on disk, and removing the rest (``sweep --gc``);
zombie runs (left RUNNING by a process that died) repaired (``status --repair``).

A checkpoint folder (``<runs.checkpoints>/<run_id>/``) is needed while
something may resume its run:

* the run is RUNNING (a live run writes it);
* its sweep cell was given back (pending: the next worker resumes it), is
  running under a claim, or failed with a retry left;
* a run of ``bronchopose train`` (no sweep claim) that ``train --resume`` can
  continue: KILLED, or FAILED by the machine (disk full, busy database).

Anything else is an orphan: a FINISHED or missing run, a run whose cell moved
on (taken over, failed for good, finished by another run), a failed run that no
retry will resume. ``last.pt.rejected`` files (refused on resume) and temporary
files of interrupted writes are never needed.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import Config
from ..errors import BronchoError, MlflowBusy, resumable
from ..io import TEMP_SUFFIX, folder_bytes
from ..runs.client import client_for
from ..runs.contract import REJECTED_SUFFIX
from ..runs.processes import repair_zombie
from ..runs.records import TAG_CELL_KEY, TAG_FAILURE, search_runs
from .storage import FAILED, PENDING, RUNNING, TAG_CLAIM, CellRow, SweepStore

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Checkpoint:
    run_id: str
    folder: Path
    bytes: int
    needed: bool
    why: str
    cell_key: str | None = None
    waste: int = 0  # bytes of never-needed files inside a needed folder (rejected checkpoints, temporary files)


def _is_waste(name: str) -> bool:
    return name.endswith(REJECTED_SUFFIX) or (name.startswith(".") and name.endswith(TEMP_SUFFIX))


def _rows_by_run(store: SweepStore | None) -> dict[str, CellRow]:
    if store is None or not store.exists():
        return {}
    return {r.run_id: r for name in store.sweeps() for r in store.rows(name) if r.run_id}


def _decide(run: Any, row: CellRow | None, max_retries: int) -> tuple[bool, str]:
    if run is None:
        return False, "no such MLflow run"
    status = run.info.status
    if status == "RUNNING":
        return True, "run RUNNING"
    if status == "FINISHED":
        return False, "run FINISHED"
    if row is not None:
        if row.state == PENDING:
            return True, "cell given back: the next worker resumes it"
        if row.state == RUNNING:
            return True, "cell running"
        if row.state == FAILED and row.retryable(max_retries):
            return True, "cell failed, a retry may resume it"
        return False, f"cell {row.state} for good"
    if run.data.tags.get(TAG_CLAIM):
        return False, "no longer the run of its sweep cell (taken over)"
    reason = run.data.tags.get(TAG_FAILURE, "")
    if status == "KILLED" or resumable(reason):
        return True, f"run {status}: `train --resume` continues it"
    return False, f"run {status}: not resumable"


def inventory(cfg: Config, store: SweepStore | None, client: Any = None) -> list[Checkpoint]:
    """Every checkpoint folder of this machine, its size, and whether a live cell needs it."""
    root = cfg.paths.checkpoints
    if not root.is_dir():
        return []
    folders = sorted(p for p in root.iterdir() if p.is_dir())
    if not folders:
        return []
    client = client or client_for(cfg)
    rows = _rows_by_run(store)
    out = []
    for folder in folders:
        try:
            run = client.get_run(folder.name)
        except MlflowBusy:
            raise
        except Exception:  # noqa: BLE001 - MLflow raises its own types for a missing run
            run = None
        needed, why = _decide(run, rows.get(folder.name), cfg.sweep.max_retries)
        key = run.data.tags.get(TAG_CELL_KEY) if run is not None else None
        out.append(Checkpoint(folder.name, folder, folder_bytes(folder), needed, why, key,
                              folder_bytes(folder, only=_is_waste) if needed else 0))
    return out


def collect_garbage(cfg: Config, store: SweepStore | None, client: Any = None) -> list[tuple[Checkpoint, int]]:
    """Remove what no live cell needs; returns each touched checkpoint and the bytes freed there."""
    freed = []
    for ck in inventory(cfg, store, client):
        if not ck.needed:
            shutil.rmtree(ck.folder, ignore_errors=True)
            freed.append((ck, ck.bytes))
            log.info("removed checkpoint %s (%s)", ck.folder, ck.why)
        elif ck.waste:
            for dirpath, _, files in os.walk(ck.folder):
                for name in files:
                    if _is_waste(name):
                        Path(dirpath, name).unlink(missing_ok=True)
            freed.append((ck, ck.waste))
    return freed


# -- zombies ---------------------------------------------------------------------------------------------------


def repair_zombies(cfg: Config, store: SweepStore | None, client: Any = None) -> list[tuple[str, str]]:
    """End the config's runs left RUNNING by a process that died; returns (run id, what was done).

    Dead on this host (its process is gone): FAILED with the reason. A sweep run whose cell is no longer
    held under the claim it was made with (the worker lost it, or released the cell without closing the
    run): KILLED. Runs alive, or on other hosts and still claimed, are left alone.
    """
    client = client or client_for(cfg)
    exp = client.get_experiment_by_name(cfg.experiment_name)
    if exp is None:
        return []
    claims = {}
    if store is not None and store.exists():
        claims = {r.token: r for name in store.sweeps() for r in store.rows(name) if r.token and r.state == RUNNING}
    done = []
    for run in search_runs(client, [exp.experiment_id], statuses=["RUNNING"]):
        token = run.data.tags.get(TAG_CLAIM)
        if token and token not in claims:
            reason = "its sweep worker no longer holds the cell's claim; marked KILLED by status --repair"
            client.set_tag(run.info.run_id, TAG_FAILURE, reason)
            client.set_terminated(run.info.run_id, "KILLED")
            done.append((run.info.run_id, "KILLED (claim gone)"))
            continue
        if token:  # still claimed: the sweep's heartbeat takeover decides
            continue
        try:
            if repair_zombie(client, run, "status --repair"):
                done.append((run.info.run_id, "FAILED (its process died)"))
        except BronchoError:  # alive
            continue
    return done
