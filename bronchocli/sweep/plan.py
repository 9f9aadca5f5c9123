"""Planning a sweep: the cells to run (grid, ``--only`` filter) and the shared state prepared once.

``prepare`` runs in the parent ``bronchopose sweep`` process before any worker
starts, so that one-time work never races between workers: the MLflow store
(its first-time schema migration) and experiment, the dataset (generated if
missing) and the claims table with one row per cell (inserted idempotently,
so several machines may plan the same sweep at once).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from .. import tracking
from ..cells import Cell, Selection, select
from ..config import Config, expand_grid
from ..generation import ensure_dataset
from ..generation.sources import planned_patients
from .storage import FAILED, FINISHED, PENDING, RUNNING, CellRow, SweepStore


def plan_cells(cfg: Config, only: Selection | None = None) -> list[Cell]:
    """The grid's cells (cross-subject folds from the dataset, or from what generation will make), filtered."""
    return select(expand_grid(cfg, planned_patients(cfg)), only or {})


@dataclass
class Plan:
    sweep: str
    cells: list[Cell]
    rows: dict[str, CellRow]  # by cell key; missing = not stored yet (pending)

    def state(self, cell: Cell) -> str:
        row = self.rows.get(cell.key)
        return row.state if row else PENDING

    def counts(self) -> dict[str, int]:
        out = {s: 0 for s in (FINISHED, RUNNING, FAILED, PENDING)}
        for c in self.cells:
            out[self.state(c)] += 1
        return out


def read_plan(store: SweepStore, sweep: str, cells: Sequence[Cell]) -> Plan:
    """The cells with their stored rows, without writing anything (``--dry-run``)."""
    rows = {r.cell_key: r for r in store.rows(sweep, [c.key for c in cells])} if store.exists() else {}
    return Plan(sweep, list(cells), rows)


def prepare(cfg: Config, store: SweepStore, only: Selection | None = None, *, sweep: str | None = None,
            dataset: bool = True, retry_failed: bool = False) -> Plan:
    """Create the shared state once (MLflow store + experiment, dataset, cell rows) and return the plan."""
    sweep = sweep or cfg.name
    tracking.experiment_id(tracking.client_for(cfg), cfg)  # MLflow's first migration happens here, once
    if dataset:
        ensure_dataset(cfg)  # before expanding: cross-subject folds come from the dataset's patients
    cells = plan_cells(cfg, only)
    store.ensure_schema()
    store.add_cells(sweep, cells)
    if retry_failed:
        store.reset_failed(sweep, [c.key for c in cells])
    return read_plan(store, sweep, cells)
