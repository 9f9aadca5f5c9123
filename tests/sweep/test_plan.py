"""Cell selection with --only, and the plan read without writing anything."""

from __future__ import annotations

import pytest

from bronchocli.config import Config, expand_grid
from bronchocli.errors import BronchoError
from bronchocli.sweep import SweepStore, parse_only, read_plan, select_cells

CFG = Config.model_validate({"name": "t", "grid": {"folds": ["p00", "p01"]}})
CELLS = expand_grid(CFG, ["p00", "p01", "p02"])  # 5 archs x 3 losses x (personalized + 2 folds) = 45


def test_only_filters_are_anded_and_values_ored():
    only = parse_only(["arch=lstm,conv3d;population=cross-subject", "fold=p01"])
    assert only == {"arch": {"lstm", "conv3d"}, "population": {"cross-subject"}, "fold": {"p01"}}
    chosen = select_cells(CELLS, only)
    assert len(chosen) == 2 * 3 and {(c.arch, c.fold) for c in chosen} == {("lstm", "p01"), ("conv3d", "p01")}
    assert select_cells(CELLS, parse_only(["rot-loss=ce", "seed=0"])) == [c for c in CELLS if c.rot_loss == "ce"]
    assert select_cells(CELLS, parse_only(["arch=lstm,baseline", "arch=lstm"])) == [c for c in CELLS
                                                                                    if c.arch == "lstm"]
    assert select_cells(CELLS, {}) == CELLS


@pytest.mark.parametrize("spec, message", [
    ("colour=red", "key one of arch"),
    ("arch", "expected key=value"),
    ("arch=", "no values"),
])
def test_malformed_only_is_rejected(spec, message):
    with pytest.raises(BronchoError, match=message):
        parse_only([spec])


def test_an_unknown_value_names_what_the_grid_has():
    with pytest.raises(BronchoError, match=r"fold=p07: .*grid has: p00, p01"):
        select_cells(CELLS, parse_only(["fold=p07"]))


def test_reading_a_plan_creates_nothing(tmp_path):
    store = SweepStore(f"sqlite:///{tmp_path}/sub/sweep.db")
    plan = read_plan(store, "t", CELLS)
    assert plan.counts() == {"finished": 0, "running": 0, "failed": 0, "pending": 45}
    assert not (tmp_path / "sub").exists()


def test_in_memory_sqlite_is_refused():
    with pytest.raises(BronchoError, match="in-memory"):
        SweepStore("sqlite://")
