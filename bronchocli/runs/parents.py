"""Parent runs: one per sweep (``run_kind=sweep``) and one per Optuna study (``run_kind=study``).

Found by tags or created once; cells and trials carry ``mlflow.parentRunId`` so the MLflow UI nests them.
A parent ends like its command (``set_parent_status``). What a parent says about its sweep or study (the
plan that ran, its outcome, the best trial) is written by the sweep package (``sweep/summary.py``,
``sweep/tuning/trial.py``) through ``log_plan_params``; ``report`` adds its tables and figures under
``report/`` (``log_report``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from pathlib import Path

from mlflow.tracking import MlflowClient

from .. import urls
from ..cells import Cell
from ..config import Config
from ..io import file_lock
from .client import MIGRATION_LOCK_KEY, database_lock
from .processes import process_tags
from .records import (
    TAG_KIND,
    TAG_NOTE,
    TAG_SWEEP,
    log_params,
    non_empty,
    python_tags,
    search_runs,
    set_tags,
    source_tags,
)
from .views import cell_params, parent_params

log = logging.getLogger(__name__)
KIND_SWEEP, KIND_STUDY = "sweep", "study"
REPORT_FOLDER = "report"  # the parent's artifact folder holding the tables and figures of `report`


def parent_run(client: MlflowClient, cfg: Config, exp_id: str, kind: str, name: str,
               params: Mapping[str, str] | None = None, description: str = "") -> str:
    """The run id of the parent run of a sweep or study ``name``: found by tags, or created once.

    Creation is serialised where the store allows it (a file lock beside a
    SQLite store, an advisory lock on PostgreSQL); against an HTTP server two
    processes starting at the same moment may each create one, and their
    children then nest under either (harmless for reports, which ignore parents).
    """
    tags = {TAG_KIND: kind, TAG_SWEEP if kind == KIND_SWEEP else "study": name}
    if kind == KIND_STUDY:
        tags[TAG_SWEEP] = cfg.name
    found = search_runs(client, [exp_id], tags, max_results=1)
    if found:
        return found[0].info.run_id
    with _creation_lock(cfg):
        found = search_runs(client, [exp_id], tags, max_results=1)
        if found:
            return found[0].info.run_id
        if line := deleted_parent_line(client, exp_id, kind, name):
            log.warning("%s; a new parent run is made now", line)
        run = client.create_run(exp_id, tags=non_empty({
            **tags, "mlflow.runName": f"{kind}-{name}", TAG_NOTE: description,
            **source_tags(cfg), **python_tags(),
        }))
        if params:
            log_params(client, run.info.run_id, params)
        return run.info.run_id


def _creation_lock(cfg: Config):
    uri = cfg.paths.mlflow_uri
    db = urls.sqlite_file(uri)
    if db is not None:
        return file_lock(f"{db}.parent.lock")
    if urls.is_postgres(uri):
        return database_lock(uri, cfg.runs.timeout_s, "runs.uri", key=PARENT_LOCK_KEY)
    return nullcontext()


PARENT_LOCK_KEY = MIGRATION_LOCK_KEY + 2  # pg_advisory_lock key of parent-run creation


def sweep_parent(client: MlflowClient, cfg: Config, exp_id: str, sweep: str | None = None) -> str:
    """The parent run of sweep ``sweep`` (default: the config's name), its grid and stages as params."""
    name = sweep or cfg.name
    return parent_run(client, cfg, exp_id, KIND_SWEEP, name, parent_params(cfg),
                      f"Sweep **{name}**: its cells are nested below; the resolved config of each cell is its "
                      "`config.yaml` artifact. This run's params state what ran (each stage's cells and "
                      "selection: `stage.<name>.*`), its metrics the outcome (`cells.*`, the best cell per stage "
                      f"by validation: `best.<stage>.*`), its `{REPORT_FOLDER}/` artifacts the tables and figures of "
                      "`bronchopose report`.")


def study_parent(client: MlflowClient, cfg: Config, exp_id: str, study: str, target: Cell) -> str:
    """The parent run of an Optuna study: the target cell's coordinates and the search space as params."""
    space = {f"tune.space.{k}": v.model_dump_json(exclude_none=True) for k, v in cfg.tune.space.items()}
    params = {**cell_params(target), **space, "tune.sampler": cfg.tune.sampler, "tune.pruner": cfg.tune.pruner}
    return parent_run(client, cfg, exp_id, KIND_STUDY, study, params,
                      f"Optuna study **{study}** of cell {target.label}: each trial is a nested run.")


def start_parent(client: MlflowClient, run_id: str) -> None:
    """A parent is RUNNING while its command runs, tagged with that command's process: a command killed outright
    (SIGKILL) leaves it RUNNING, and ``status --repair`` (or the next command) sees the process gone and ends it."""
    client.update_run(run_id, "RUNNING")
    set_tags(client, run_id, process_tags())  # every worker of a sweep tags the parent as it starts


def set_parent_status(client: MlflowClient, run_id: str, code: int) -> None:
    """A sweep's or study's parent ends like its command: 0 FINISHED, 130 KILLED, anything else FAILED.

    Best effort: an MLflow store gone at the end must not hide the command's own outcome.
    """
    try:
        client.set_terminated(run_id, "FINISHED" if code == 0 else "KILLED" if code == 130 else "FAILED")
    except Exception as exc:  # noqa: BLE001 - logged; the children carry the results
        log.warning("could not end parent run %s: %s", run_id, exc)


def find_parent(client: MlflowClient, exp_id: str, kind: str, name: str) -> str | None:
    """The run id of an existing parent (sweep or study ``name``); None when there is none (nothing created)."""
    found = search_runs(client, [exp_id], {TAG_KIND: kind, TAG_SWEEP if kind == KIND_SWEEP else "study": name},
                        max_results=1)
    return found[0].info.run_id if found else None


def deleted_parent_line(client: MlflowClient, exp_id: str, kind: str, name: str) -> str | None:
    """One line when the parent of sweep or study ``name`` was deleted by hand (None: it was not): what to do."""
    tags = {TAG_KIND: kind, TAG_SWEEP if kind == KIND_SWEEP else "study": name}
    found = search_runs(client, [exp_id], tags, max_results=1, deleted=True)
    if not found:
        return None
    return (f"the parent run {found[0].info.run_id} of {kind} {name!r} was deleted (in the MLflow UI): restore it "
            f"there (the runs list, 'deleted') to keep the cells nested under it, or the next `bronchopose "
            f"{'sweep run' if kind == KIND_SWEEP else 'tune'}` makes a new one")


def log_plan_params(client: MlflowClient, run_id: str, params: Mapping[str, str]) -> list[str]:
    """Log the params the parent does not have yet; returns the keys whose logged value differs.

    MLflow params never change, and a sweep keeps its parent when its config changes (cells are found by
    key, not by plan). A differing value is set as a tag of the same key instead (the UI shows tags
    beside params), with one warning: the params then say what ran first, the tags what the latest plan says.
    """
    have = client.get_run(run_id).data.params
    new = {k: v for k, v in params.items() if k not in have}
    changed = {k: v for k, v in params.items() if k in have and have[k] != str(v)[:6000]}
    if new:
        log_params(client, run_id, new)
    set_tags(client, run_id, changed)
    if changed:
        log.warning("the plan changed since parent run %s logged it (%s): its params keep the first values, "
                    "its tags of the same names hold the latest", run_id, ", ".join(sorted(changed)))
    return sorted(changed)


def log_report(client: MlflowClient, run_id: str, folder: str | Path, files: Sequence[str | Path]) -> int:
    """The report's ``files`` (under ``folder``) as the parent's artifacts under ``report/``, same layout;
    returns how many were logged."""
    folder = Path(folder)
    n = 0
    for f in files:
        rel = Path(f).resolve().relative_to(folder.resolve())
        sub = (Path(REPORT_FOLDER) / rel.parent).as_posix()
        client.log_artifact(run_id, str(f), sub)
        n += 1
    return n
