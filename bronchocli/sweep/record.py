"""MLflow is the record of what finished; the claims table only coordinates who runs what.

A cell with a FINISHED MLflow run (``run_kind=cell``, its ``cell_key`` and ``sweep`` tags) is never trained
again, whatever the claims table says: a lost or new claims database, a table behind (the cell finished by
``bronchopose train``), or a row given back. Three places ask:

* ``rebuild``: whenever the sweep adds its cells' rows (``plan.add_cells``: every launcher, every array task),
  rows that are pending or failed but FINISHED in MLflow are recorded FINISHED, with that run (worker column
  ``REBUILT``), before any worker can claim them;
* ``Worker`` checks the cell it just claimed (a stale claim it took over too: a worker killed between ending its
  run and writing the row, or whose row write failed), and records the FINISHED run instead of training;
* ``overlay``: ``sweep plan`` and ``status`` show the same, without writing anything.

A study that is new in its storage gets the trials MLflow records FINISHED for it (``rebuild_trials``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

from mlflow.exceptions import MlflowException

from .. import runkeys, urls
from ..cells import Cell
from ..config import Config, TuneParam
from ..errors import MlflowBusy
from ..runs.client import ExperimentDeleted, client_for, find_experiment, redacted_uri
from ..runs.records import TAG_KIND, TAG_SWEEP, deleted_runs_line, finished_cell_runs, search_runs
from .storage import FAILED, FINISHED, PENDING, CellRow, SweepStore

log = logging.getLogger(__name__)

REBUILT = "rebuilt from MLflow"  # the worker column of a row recorded from a FINISHED MLflow run


def duration_of(run: Any) -> float | None:
    """A finished run's duration in seconds (None when MLflow lacks its start or end)."""
    info = run.info
    return (info.end_time - info.start_time) / 1000 if info.end_time and info.start_time else None


def finished_runs(cfg: Config, keys: Sequence[str], sweep: str | None = None, client: Any = None) -> dict[str, Any]:
    """The FINISHED MLflow run of each of ``keys`` that has one. Reads only: a SQLite store that does not exist
    yet, or an experiment not created yet, holds none (nothing is created to find that out)."""
    if not keys:
        return {}
    if client is None:
        db = urls.sqlite_file(cfg.paths.mlflow_uri)
        if db is not None and not db.is_file():
            return {}
        client = client_for(cfg, reading=True)
    exp = find_experiment(client, cfg.experiment_name, redacted_uri(cfg))  # deleted by hand: one line, never guessed
    if exp is None:
        return {}
    return finished_cell_runs(client, exp.experiment_id, sweep or cfg.name, keys)


def _reader(cfg: Config) -> Any:
    """A reading client of the config's store and its experiment, or (None, None) when neither exists yet."""
    db = urls.sqlite_file(cfg.paths.mlflow_uri)
    if db is not None and not db.is_file():
        return None, None
    client = client_for(cfg, reading=True)
    return client, find_experiment(client, cfg.experiment_name, redacted_uri(cfg))


def existing_experiment(cfg: Config) -> tuple[Any, Any]:
    """A reading client of the config's store and its experiment; (None, None) when neither exists yet (nothing is
    created to find that out)."""
    return _reader(cfg)


def check_experiment(cfg: Config) -> None:
    """``ExperimentDeleted`` (one line) when the config's experiment was deleted by hand; reads only."""
    _reader(cfg)


def deleted_finished(cfg: Config, sweep: str, rows: Mapping[str, CellRow]) -> dict[str, CellRow]:
    """The rows recorded FINISHED whose run was deleted by hand (the MLflow UI), by cell key: MLflow says the cell
    has no run, so it is not done (``forget_deleted``; status shows it so: ``overlay``)."""
    finished = {r.run_id: r for r in rows.values() if r.state == FINISHED and r.run_id and r.damage is None}
    if not finished:
        return {}
    client, exp = _reader(cfg)
    if exp is None:
        return {}
    gone = search_runs(client, [exp.experiment_id], {TAG_SWEEP: sweep, TAG_KIND: "cell"}, deleted=True)
    return {finished[r.info.run_id].cell_key: finished[r.info.run_id] for r in gone if r.info.run_id in finished}


def forget_deleted(cfg: Config, store: SweepStore, sweep: str, cells: Sequence[Cell]) -> int:
    """Make pending again every row recorded FINISHED whose run was deleted by hand (one line says so and what to
    do); ``rebuild`` then records another FINISHED run of the cell if there is one, else a worker trains it."""
    rows = {r.cell_key: r for r in store.rows(sweep, [c.key for c in cells])}
    try:
        gone = deleted_finished(cfg, sweep, rows)
    except (MlflowBusy, ExperimentDeleted):
        raise
    except Exception as exc:  # noqa: BLE001 - the store unread: the table stays as it is
        log.warning("could not read MLflow's deleted runs of sweep %s: %s", sweep, exc)
        return 0
    n = sum(1 for row in gone.values() if store.repair(row))
    if n:
        log.warning("%s", deleted_runs_line(n, sweep, cfg.experiment_name, now=True))
    return n


def missing_runs(cfg: Config, run_ids: Sequence[str]) -> list[str]:
    """The ``run_ids`` MLflow does not have at all (another store than the sweep ran in, or removed for good by
    ``mlflow gc``); a store that cannot be asked has none missing."""
    if not run_ids:
        return []
    try:
        client, _ = _reader(cfg)
    except Exception as exc:  # noqa: BLE001 - a store that cannot be asked: nothing is said missing
        log.warning("could not ask MLflow for the claims table's runs: %s", exc)
        return []
    if client is None:
        return []
    out = []
    for run_id in run_ids:
        try:
            client.get_run(run_id)
        except MlflowException as exc:
            if exc.error_code == "RESOURCE_DOES_NOT_EXIST":
                out.append(run_id)
        except Exception:  # noqa: BLE001 - busy or away: not known missing
            continue
    return out


def missing_line(row: CellRow, where: str) -> str:
    """One line: a claims row whose run MLflow does not have, and what to do."""
    return (f"claims row {row.sweep}/{row.cell_key} ({row.label}): its run {row.run_id} does not exist in MLflow "
            f"store {where} (another store than the sweep ran in, or removed for good by `mlflow gc`): check "
            "runs.uri; `bronchopose status --repair` makes the cell pending again, so the next sweep trains it")


def _open_rows(rows: dict[str, CellRow], cells: Sequence[Cell]) -> list[Cell]:
    """Cells no worker holds and that are not recorded FINISHED: those MLflow may know better."""
    return [c for c in cells if c.key not in rows or rows[c.key].state in (PENDING, FAILED)]


def rebuild(cfg: Config, store: SweepStore, sweep: str, cells: Sequence[Cell]) -> int:
    """Record FINISHED every pending or failed row whose cell has a FINISHED MLflow run; returns how many."""
    rows = {r.cell_key: r for r in store.rows(sweep, [c.key for c in cells])}
    todo = [c for c in _open_rows(rows, cells) if c.key in rows]
    try:
        found = finished_runs(cfg, [c.key for c in todo], sweep)
    except (MlflowBusy, ExperimentDeleted):
        raise
    except Exception as exc:  # noqa: BLE001 - the worker's own check still stops a second training
        log.warning("could not read MLflow's finished runs of sweep %s: %s", sweep, exc)
        return 0
    n = 0
    for c in todo:
        run = found.get(c.key)
        if run is not None and store.record_finished(rows[c.key], run.info.run_id, duration_of(run), REBUILT):
            log.info("cell %s: FINISHED in MLflow (run %s), recorded in the claims table", c.label, run.info.run_id)
            n += 1
    return n


def overlay(cfg: Config, sweep: str, cells: Sequence[Cell], rows: dict[str, CellRow],
            deleted: Mapping[str, CellRow] | None = None) -> tuple[dict[str, CellRow], int]:
    """``rows`` with the cells FINISHED in MLflow shown FINISHED (nothing written); returns them and how many.
    ``deleted`` (``deleted_finished``): rows whose run was deleted by hand, shown pending (as a sweep makes them)."""
    rows = {**rows, **{k: replace(r, state=PENDING, run_id=None, attempts=0, worker=None, duration_s=None)
                       for k, r in (deleted or {}).items()}}
    todo = _open_rows(rows, cells)
    try:
        found = finished_runs(cfg, [c.key for c in todo], sweep)
    except ExperimentDeleted:
        raise
    except Exception as exc:  # noqa: BLE001 - a view: show the claims table alone
        log.warning("could not read MLflow's finished runs: %s", exc)
        return rows, 0
    out = dict(rows)
    for i, c in enumerate(cells):
        run = found.get(c.key)
        if run is None:
            continue
        base = out.get(c.key) or CellRow(sweep, c.key, i, c.label, c.coords(), PENDING, 0, 0, None, None, None, None,
                                         None, None, None, None, None)
        out[c.key] = replace(base, state=FINISHED, run_id=run.info.run_id, worker=REBUILT, token=None,
                             duration_s=duration_of(run), failure_reason=None)
    return out, len(found)


def rebuilt_count(rows: dict[str, CellRow]) -> int:
    """Rows recorded from MLflow rather than by the worker that ran them."""
    return sum(1 for r in rows.values() if r.state == FINISHED and r.worker == REBUILT)


# -- Optuna studies ------------------------------------------------------------------------------------------


def distributions(space: Mapping[str, TuneParam]) -> dict[str, Any]:
    """``tune.space`` as Optuna distributions (what ``tuning.trial.suggest`` samples)."""
    from optuna import distributions as d  # lazy: optuna only where a study is tuned, not in every sweep

    out: dict[str, Any] = {}
    for path, p in space.items():
        if p.type == "float":
            out[path] = d.FloatDistribution(p.low, p.high, log=p.log, step=p.step)
        elif p.type == "int":
            out[path] = d.IntDistribution(int(p.low), int(p.high), log=p.log, step=int(p.step or 1))
        else:
            out[path] = d.CategoricalDistribution(p.choices)
    return out


def _param(raw: str | None, dist: Any) -> Any:
    """A trial's value of one parameter, from the MLflow param its run logged (a string)."""
    if raw is None:
        raise ValueError("not logged")
    if hasattr(dist, "choices"):
        return next(c for c in dist.choices if str(c) == raw)
    return int(float(raw)) if type(dist).__name__ == "IntDistribution" else float(raw)


def rebuild_trials(cfg: Config, study: Any, attr_run: str) -> int:
    """A new (or lost) study gets the trials MLflow records as FINISHED for it, as COMPLETE trials with their
    parameters and best validation loss (user attribute ``attr_run``: the run), so none is run again."""
    from optuna.trial import create_trial  # lazy: optuna only where a study is tuned, not in every sweep

    if study.get_trials(deepcopy=False):
        return 0
    db = urls.sqlite_file(cfg.paths.mlflow_uri)
    if db is not None and not db.is_file():
        return 0
    client = client_for(cfg)
    exp = client.get_experiment_by_name(cfg.experiment_name)
    if exp is None:
        return 0
    runs = search_runs(client, [exp.experiment_id], {TAG_KIND: "trial", "study": study.study_name}, ["FINISHED"])
    dists, n = distributions(cfg.tune.space), 0
    for run in sorted(runs, key=lambda r: r.info.start_time or 0):
        try:
            params = {k: _param(run.data.params.get(k), dist) for k, dist in dists.items()}
            study.add_trial(create_trial(params=params, distributions=dists, value=run.data.metrics.get(
                runkeys.best_of(runkeys.VAL_LOSS)), user_attrs={attr_run: run.info.run_id, "rebuilt": "mlflow"}))
        except (ValueError, StopIteration, TypeError):  # another search space, or no finite loss: not this study's
            continue
        n += 1
    if n:
        log.warning("study %s was new: %d finished trial(s) rebuilt from MLflow", study.study_name, n)
    return n
