"""The plan read without writing anything, and storage that cannot be shared."""

from __future__ import annotations

import pytest

from bronchocli.config import Config, expand_grid
from bronchocli.errors import BronchoError
from bronchocli.sweep import SweepStore, read_plan

CFG = Config.model_validate({"name": "t", "grid": {"folds": ["p00", "p01"], "seed": [0]}})
CELLS = expand_grid(CFG, ["p00", "p01", "p02"])  # 5 archs x 3 losses x (personalized + 2 folds) = 45


def test_reading_a_plan_creates_nothing(tmp_path):
    store = SweepStore(f"sqlite:///{tmp_path}/sub/sweep.db")
    plan = read_plan(store, "t", CELLS)
    assert plan.counts() == {"finished": 0, "running": 0, "failed": 0, "pending": 45}
    assert not (tmp_path / "sub").exists()


def test_in_memory_sqlite_is_refused():
    with pytest.raises(BronchoError, match="in-memory"):
        SweepStore("sqlite://")
