"""MLflow is the record of what finished; the claims table only coordinates who runs what.

A cell with a FINISHED MLflow run (``run_kind=cell``, its ``cell_key`` and ``sweep`` tags) is never trained
again, whatever the claims table says: a lost or new claims database, a table behind (the cell finished by
``bronchopose train``), or a row given back. Three places ask:

* ``rebuild``: whenever the sweep adds its cells' rows (``plan.add_cells``: every launcher, every array task),
  rows that are pending or failed but FINISHED in MLflow are recorded FINISHED, with that run (worker column
  ``REBUILT``), before any worker can claim them;
* ``Worker`` checks the cell it just claimed, and records the FINISHED run instead of training;
* ``overlay``: ``sweep --dry-run`` and ``status`` show the same, without writing anything.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

from .. import urls
from ..cells import Cell
from ..config import Config
from ..errors import MlflowBusy
from ..runs.client import client_for
from ..runs.records import finished_cell_runs
from .storage import FAILED, FINISHED, PENDING, CellRow, SweepStore

log = logging.getLogger(__name__)

REBUILT = "rebuilt from MLflow"  # the worker column of a row recorded from a FINISHED MLflow run


def _duration(run: Any) -> float | None:
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
    exp = client.get_experiment_by_name(cfg.experiment_name)
    if exp is None:
        return {}
    return finished_cell_runs(client, exp.experiment_id, sweep or cfg.name, keys)


def _open_rows(rows: dict[str, CellRow], cells: Sequence[Cell]) -> list[Cell]:
    """Cells no worker holds and that are not recorded FINISHED: those MLflow may know better."""
    return [c for c in cells if c.key not in rows or rows[c.key].state in (PENDING, FAILED)]


def rebuild(cfg: Config, store: SweepStore, sweep: str, cells: Sequence[Cell]) -> int:
    """Record FINISHED every pending or failed row whose cell has a FINISHED MLflow run; returns how many."""
    rows = {r.cell_key: r for r in store.rows(sweep, [c.key for c in cells])}
    todo = [c for c in _open_rows(rows, cells) if c.key in rows]
    try:
        found = finished_runs(cfg, [c.key for c in todo], sweep)
    except MlflowBusy:
        raise
    except Exception as exc:  # noqa: BLE001 - the worker's own check still stops a second training
        log.warning("could not read MLflow's finished runs of sweep %s: %s", sweep, exc)
        return 0
    n = 0
    for c in todo:
        run = found.get(c.key)
        if run is not None and store.record_finished(rows[c.key], run.info.run_id, _duration(run), REBUILT):
            log.info("cell %s: FINISHED in MLflow (run %s), recorded in the claims table", c.label, run.info.run_id)
            n += 1
    return n


def overlay(cfg: Config, sweep: str, cells: Sequence[Cell], rows: dict[str, CellRow]) -> tuple[dict[str, CellRow], int]:
    """``rows`` with the cells FINISHED in MLflow shown FINISHED (nothing written); returns them and how many."""
    todo = _open_rows(rows, cells)
    try:
        found = finished_runs(cfg, [c.key for c in todo], sweep)
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
                             duration_s=_duration(run), failure_reason=None)
    return out, len(found)


def rebuilt_count(rows: dict[str, CellRow]) -> int:
    """Rows recorded from MLflow rather than by the worker that ran them."""
    return sum(1 for r in rows.values() if r.state == FINISHED and r.worker == REBUILT)
