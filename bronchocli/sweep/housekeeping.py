"""Which checkpoints are still needed, what they cost on disk, and removing the rest (``sweep gc``);
zombie runs (left RUNNING by a process that died) repaired (``status --repair``).

A checkpoint folder (``<runs.checkpoints>/<run_id>/``) is needed while
something may resume its run:

* the run is RUNNING (a live run writes it);
* its sweep cell was given back (pending: the next worker resumes it), is
  running under a claim, or failed with a retry left;
* a run of ``bronchopose train`` (no sweep claim) that ``train --resume`` can
  continue: KILLED, or FAILED by the machine (disk full, busy database);
* a tune trial's run (KILLED or FAILED) while a trial of its study waits to
  resume it (``tuning.resume.checkpoint_need``): once that trial ran, or the
  study's parent run FINISHED without it, or no trial was ever handed it
  (an interruption before this was kept), the checkpoint is reclaimable. A study
  not in ``storage.url`` (or a storage that cannot be read) keeps it: it may
  live in another storage (``gc --storage URL``).

Anything else is an orphan: a FINISHED or missing run, a run whose cell moved
on (taken over, failed for good, finished by another run), a failed run that no
retry will resume. ``last.pt.rejected`` files (refused on resume) and temporary
files of interrupted writes are never needed.

Only folders provably written by a run are looked at, and only the files a run
wrote there are removed (``runs.ownership``: its marker, or its ``last.pt``
read back); anything else in ``runs.checkpoints`` (a user's folder, MLflow's
artifacts, a foreign file) is never touched and is listed by ``foreign``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from .. import urls
from ..config import Config
from ..errors import BronchoError, MlflowBusy, resumable
from ..runs.client import client_for
from ..runs.ownership import owned_checkpoint, removable_bytes, remove_checkpoint
from ..runs.processes import repair_zombie
from ..runs.records import TAG_CELL_KEY, TAG_FAILURE, TAG_KIND, TAG_PARENT, search_runs
from .storage import FAILED, PENDING, RUNNING, TAG_CLAIM, CellRow, StorageError, SweepStore
from .tuning.resume import checkpoint_need

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Checkpoint:
    run_id: str
    folder: Path
    bytes: int  # of the files the run wrote there (what removing it frees; anything else inside is kept)
    needed: bool
    why: str
    cell_key: str | None = None
    waste: int = 0  # bytes of never-needed files inside a needed folder (rejected checkpoints, temporary files)


def _rows_by_run(store: SweepStore | None) -> dict[str, CellRow]:
    if store is None or not store.exists():
        return {}
    return {r.run_id: r for name in store.sweeps() for r in store.rows(name) if r.run_id}


def _decide(run: Any, row: CellRow | None, max_retries: int,
            trial: Callable[[Any], tuple[bool, str]] | None = None) -> tuple[bool, str]:
    """Whether a run's checkpoint is needed, and why (``trial``: the decision for a tune trial's run)."""
    if run is None:
        return False, "no such MLflow run"
    status = run.info.status
    if status == "RUNNING":
        return True, "run RUNNING"
    if status == "FINISHED":
        return False, "run FINISHED"
    if trial is not None and run.data.tags.get(TAG_KIND) == "trial" and run.data.tags.get("study"):
        return trial(run)
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


def _entries(cfg: Config) -> list[Path]:
    root = cfg.paths.checkpoints
    if root.is_symlink() or not root.is_dir():
        return []
    return sorted(root.iterdir())


def foreign(cfg: Config) -> list[Path]:
    """What lies in ``runs.checkpoints`` but is not provably a checkpoint folder of this project (never touched)."""
    return [p for p in _entries(cfg) if owned_checkpoint(p) is None]


def _open_client(cfg: Config) -> Any:
    """A client of the config's MLflow store; None when its SQLite file does not exist (nothing is created)."""
    db = urls.sqlite_file(cfg.paths.mlflow_uri)
    return None if db is not None and not db.is_file() else client_for(cfg, reading=True)


class _Studies:
    """The studies of ``storage.url`` that trial checkpoints belong to, each read once (Optuna loads only here)."""

    def __init__(self, cfg: Config, client: Any) -> None:
        self.cfg, self.client, self.trials = cfg, client, {}

    def _trials(self, name: str) -> list[Any] | str:
        if name not in self.trials:
            from .tuning import studies  # lazy: Optuna only where a trial's checkpoint lies, not for every status

            try:
                self.trials[name] = studies.load(self.cfg, name).get_trials(deepcopy=False)
            except StorageError as exc:
                self.trials[name] = f"its study {name}'s storage could not be read ({exc})"
            except BronchoError:
                self.trials[name] = (f"study {name} is not in storage.url {urls.redact(self.cfg.paths.storage_url)} "
                                     "(it may live in another: `sweep gc --storage URL` decides)")
        return self.trials[name]

    def __call__(self, run: Any) -> tuple[bool, str]:
        name = run.data.tags["study"]
        trials = self._trials(name)
        if isinstance(trials, str):
            return True, trials
        parent = None
        if run.data.tags.get(TAG_PARENT):
            try:
                parent = self.client.get_run(run.data.tags[TAG_PARENT]).info.status
            except MlflowBusy:
                raise
            except Exception:  # noqa: BLE001 - a parent run deleted: the study is not known to be done
                parent = None
        return checkpoint_need(trials, run.info.run_id, name, parent)


def inventory(cfg: Config, store: SweepStore | None, client: Any = None) -> list[Checkpoint]:
    """Every checkpoint folder of this machine provably written by a run, its size, and whether a live cell
    needs it (anything else in ``runs.checkpoints`` is not a checkpoint: ``foreign`` lists it)."""
    owned = [o for o in map(owned_checkpoint, _entries(cfg)) if o is not None]
    if not owned:
        return []
    client = client or _open_client(cfg)
    rows = _rows_by_run(store)
    studies = _Studies(cfg, client)
    out = []
    for o in owned:
        run = None
        if client is not None:
            try:
                run = client.get_run(o.folder.name)
            except MlflowBusy:
                raise
            except Exception:  # noqa: BLE001 - MLflow raises its own types for a missing run
                run = None
        needed, why = _decide(run, rows.get(o.folder.name), cfg.sweep.max_retries, studies)
        key = run.data.tags.get(TAG_CELL_KEY) if run is not None else None
        out.append(Checkpoint(o.folder.name, o.folder, removable_bytes(o.folder), needed, why, key,
                              removable_bytes(o.folder, only_waste=True) if needed else 0))
    return out


def collect_garbage(cfg: Config, store: SweepStore | None, client: Any = None, *, dry_run: bool = False,
                    held: list[Checkpoint] | None = None) -> list[tuple[Checkpoint, int]]:
    """Remove what no live cell needs (``dry_run``: only say what would go); returns each touched checkpoint and
    the bytes freed there. Only files a run wrote in its own folder are removed (``runs.ownership``). ``held``:
    the ``inventory`` already taken."""
    freed = []
    for ck in inventory(cfg, store, client) if held is None else held:
        if not ck.needed:
            n = ck.bytes if dry_run else remove_checkpoint(ck.folder, ck.why)
            freed.append((ck, n))
        elif ck.waste:
            n = ck.waste if dry_run else remove_checkpoint(ck.folder, ck.why, only_waste=True)
            freed.append((ck, n))
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
