"""Claims rows this code cannot use, and heartbeats from the future: one line each, and ``status --repair``.

A claims row changed by hand or by another tool (a state the code does not know, coords that are not JSON, a
column that is not a number: ``storage.CellRow.damage``) is read all the same and set aside: no worker claims
it, no command stops on it, and every command that shows the sweep says, in one line naming the row, what is
wrong and what to do. ``status --repair`` (``repair``) makes it pending again (a FINISHED MLflow run of its
cell is recorded again by the next sweep, ``record.rebuild``), or deletes it when no cell of the plan can
rebuild it (its coords damaged, and not a cell of this config: its MLflow runs are kept).

A heartbeat ahead of the database's clock (a skewed clock where SQLite's clock is each machine's own, or a hand
edit) is no damage: the claim is live while its heartbeat changes, and a worker takes it over once it saw it
unchanged for ``sweep.stale_after_s`` of its own clock (``liveness.FutureHeartbeats``).
"""

from __future__ import annotations

from collections.abc import Sequence

from ..cells import Cell
from .storage import RUNNING, CellRow, SweepStore

REPAIR = "`bronchopose status --repair` makes it pending again"


def damage_line(row: CellRow, where: str) -> str:
    """One line: the damaged row (sweep, cell key, label), what is wrong, and what to do."""
    return (f"claims row {row.sweep}/{row.cell_key} ({row.label}) in {where}: {row.damage}; set aside (not run); "
            f"{REPAIR} (a FINISHED MLflow run of the cell is kept and recorded), or correct that cell's row by hand")


def future_s(row: CellRow, now: float | None) -> float | None:
    """How far a running claim's heartbeat lies ahead of the database's clock ``now`` (None: not ahead)."""
    if row.damage is None and row.state == RUNNING and now is not None and row.heartbeat is not None \
            and row.heartbeat > now + 1.0:
        return row.heartbeat - now
    return None


def future_line(row: CellRow, ahead_s: float, stale_after_s: float) -> str:
    """One line: a claim whose heartbeat lies in the future, and when another worker takes its cell over."""
    return (f"claims row {row.sweep}/{row.cell_key} ({row.label}): heartbeat {ahead_s:.0f} s ahead of the database's "
            f"clock (worker {row.worker}: its machine's clock is ahead, or the row was edited); a sweep takes the "
            f"cell over once it sees it unchanged for sweep.stale_after_s ({stale_after_s:g} s) of its own clock")


def damaged(rows: Sequence[CellRow]) -> list[CellRow]:
    return [r for r in rows if r.damage is not None]


def repair(store: SweepStore, sweep: str, cells: Sequence[Cell]) -> list[tuple[CellRow, str]]:
    """``status --repair``: every damaged row of ``sweep`` pending again (coords and label from the plan's
    ``cells`` when its own are damaged), or deleted when neither it nor the plan can say which cell it is;
    returns each row with what was done. A row changed meanwhile is left for the next repair."""
    plan = {c.key: c for c in cells}
    done = []
    for row in damaged(store.rows(sweep)):
        cell = plan.get(row.cell_key)
        coords_bad = "coords" in (row.damage or "")
        if coords_bad and cell is None:
            if store.delete(row):
                done.append((row, "deleted (its coords are damaged and it is no cell of this config; its MLflow "
                                  "runs are kept)"))
            continue
        coords = cell.coords() if coords_bad and cell is not None else None
        if store.repair(row, cell.label if cell is not None else None, coords):
            done.append((row, "pending again"))
    return done
