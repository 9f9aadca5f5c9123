"""Planning a sweep: the cells to run (grid, ``--only`` filter) and the shared state prepared once.

``prepare`` runs in the parent ``bronchopose sweep`` process before any worker
starts, so that one-time work never races between workers: the MLflow store
(its first-time schema migration) and experiment, the dataset (generated if
missing) and the claims table with one row per cell (inserted idempotently,
so several machines may plan the same sweep at once).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from .. import tracking
from ..config import Cell, Config, expand_grid
from ..errors import BronchoError
from .storage import FAILED, FINISHED, PENDING, RUNNING, CellRow, SweepStore

ONLY_KEYS = ("arch", "rot_loss", "population", "fold", "seed", "pose_frame")


def parse_only(specs: Iterable[str] | None) -> dict[str, set[str]]:
    """``["arch=lstm,conv3d;population=personalized", "seed=0"]`` -> ``{"arch": {...}, ...}`` (AND of keys)."""
    out: dict[str, set[str]] = {}
    for spec in specs or []:
        for part in filter(None, (p.strip() for p in spec.split(";"))):
            key, sep, values = part.partition("=")
            key = key.strip().replace("-", "_")
            if not sep or key not in ONLY_KEYS:
                raise BronchoError(f"--only {part!r}: expected key=value[,value...] with key one of "
                                   f"{', '.join(ONLY_KEYS)}")
            vals = {v.strip() for v in values.split(",") if v.strip()}
            if not vals:
                raise BronchoError(f"--only {part!r}: no values given")
            out[key] = out[key] & vals if key in out else vals
    return out


def _value(cell: Cell, key: str) -> str:
    v = getattr(cell, key)
    return "" if v is None else str(v)


def select_cells(cells: Sequence[Cell], only: dict[str, set[str]]) -> list[Cell]:
    """Cells matching every ``--only`` key; a value no cell has is an error (likely a typo)."""
    for key, vals in only.items():
        known = {_value(c, key) for c in cells}
        unknown = sorted(vals - known)
        if unknown:
            shown = ", ".join(sorted(v for v in known if v)) or "none"
            raise BronchoError(f"--only {key}={','.join(unknown)}: no cell of the grid has that {key} "
                               f"(grid has: {shown})")
    return [c for c in cells if all(_value(c, k) in v for k, v in only.items())]


def plan_cells(cfg: Config, only: dict[str, set[str]] | None = None) -> list[Cell]:
    from ..data.naming import patient_ids_for

    return select_cells(expand_grid(cfg, patient_ids_for(cfg)), only or {})


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


def prepare(cfg: Config, store: SweepStore, only: dict[str, set[str]] | None = None, *, sweep: str | None = None,
            dataset: bool = True, retry_failed: bool = False) -> Plan:
    """Create the shared state once (MLflow store + experiment, dataset, cell rows) and return the plan."""
    sweep = sweep or cfg.name
    tracking.experiment_id(tracking.client_for(cfg), cfg)  # MLflow's first migration happens here, once
    if dataset:
        from ..data.generate import ensure_dataset

        ensure_dataset(cfg)  # before expanding: cross-subject folds come from the dataset's patients
    cells = plan_cells(cfg, only)
    store.ensure_schema()
    store.add_cells(sweep, cells)
    if retry_failed:
        store.reset_failed(sweep, [c.key for c in cells])
    return read_plan(store, sweep, cells)
