"""The plan read without writing anything, storage that cannot be shared, and the status table."""

from __future__ import annotations

from io import StringIO

import pytest
from rich.console import Console

from bronchocli.config import Config, expand_grid
from bronchocli.errors import BronchoError
from bronchocli.runs.records import run_name
from bronchocli.sweep import FINISHED, RUNNING, SweepStore, read_plan
from bronchocli.sweep.plan import Plan
from bronchocli.sweep.status import status_table
from bronchocli.sweep.storage import CellRow

CFG = Config.model_validate({"name": "t", "grid": {"folds": ["p00", "p01"], "seed": [0]}})
CELLS = expand_grid(CFG, ["p00", "p01", "p02"])  # 5 archs x 3 losses x (personalized + 2 folds) = 45


def test_reading_a_plan_creates_nothing(tmp_path):
    store = SweepStore(f"sqlite:///{tmp_path}/sub/sweep.db")
    plan = read_plan(store, "t", CELLS)
    assert plan.counts() == {"finished": 0, "running": 0, "failed": 0, "pending": 45, "damaged": 0}
    assert not (tmp_path / "sub").exists()


def test_in_memory_sqlite_is_refused():
    with pytest.raises(BronchoError, match="in-memory"):
        SweepStore("sqlite://")


def test_status_shows_a_running_cells_elapsed_time_and_share_of_its_budget():
    def row(cell, state, **kw):
        base = dict(sweep="t", cell_key=cell.key, ord=0, label=cell.label, coords=cell.coords(), state=state,
                    attempts=1, version=1, worker="vm:1", token="x", heartbeat=None, claimed_at=None,
                    finished_at=None, created_at=None, run_id=None, failure_reason=None, duration_s=None)
        return CellRow(**{**base, **kw})

    running, done, fresh = CELLS[:3]
    plan = Plan("t", [running, done, fresh], {
        running.key: row(running, RUNNING, claimed_at=1000.0, run_id="r1"),
        done.key: row(done, FINISHED, run_id="r2", duration_s=75.0),
        fresh.key: row(fresh, RUNNING, claimed_at=1290.0, run_id="r3"),  # no validation logged yet
    })
    metrics = {"r1": {"pairs_seen": 4800.0}, "r2": {"pairs_seen": 6400.0, "pair.pos_l2.mean": 1.5}}
    out = StringIO()
    Console(file=out, width=250).print(status_table(plan, metrics, 1, budget_pairs=6400, now=1300.0))
    # each row opens with its run's name (records.run_name: the model, its seed, then the coordinates)
    text = out.getvalue().splitlines()

    def line(cell) -> str:
        (found,) = [row for row in text if row.strip().startswith(run_name(cell)[:24])]
        return found

    assert len({run_name(c)[:24] for c in (running, done, fresh)}) == 3
    assert "5m00s, 75% trained" in line(running)
    assert "1m15s" in line(done) and "trained" not in line(done)
    assert "10s" in line(fresh) and "trained" not in line(fresh)
