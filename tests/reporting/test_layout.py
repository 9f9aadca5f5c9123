"""Number formatting and the paper's highlighting rules on hand-made tables."""

from __future__ import annotations

from bronchocli.metrics import Stat
from bronchocli.reporting.layout import Column, Row, Table, cell_texts, column_decimals, marks, missing_cells


def _table(values: list[list[float | None]], groups: list[str], highlight=True) -> Table:
    rows = [Row(g, f"r{i}", [None if v is None else Stat(v, v / 10, 3) for v in vals])
            for i, (g, vals) in enumerate(zip(groups, values))]
    cols = [Column(f"c{j}", highlight=highlight) for j in range(len(values[0]))]
    return Table("t", "T", ("Network", "Loss"), cols, rows)


def test_best_second_and_group_marks():
    t = _table([[3.0], [1.0], [2.0], [5.0], [4.0]], ["A", "A", "A", "B", "B"])
    m = [row[0] for row in marks(t)]
    assert m == [set(), {"best", "group"}, {"second"}, set(), {"group"}]


def test_ties_as_displayed_share_the_mark():
    # 1.0001 and 1.0004 print as 1.00: both are best; 1.5 is second.
    t = _table([[1.0001], [1.0004], [1.5]], ["A", "B", "C"])
    assert [row[0] for row in marks(t)] == [{"best"}, {"best"}, {"second"}]
    assert cell_texts(t)[0][0] == "1.00 ± 0.10"


def test_no_marks_with_a_single_value_or_unranked_column():
    t = _table([[2.0], [None], [3.0]], ["A", "A", "B"])
    m = [row[0] for row in marks(t)]
    assert m == [{"best"}, set(), {"second"}]  # group A has one value: no bold; group B alone: no bold
    single = _table([[2.0], [None]], ["A", "A"])
    assert [row[0] for row in marks(single)] == [set(), set()]
    plain = _table([[2.0], [1.0]], ["A", "A"], highlight=False)
    assert [row[0] for row in marks(plain)] == [set(), set()]


def test_decimals_follow_the_smallest_value_of_the_column():
    t = _table([[0.000123, 45.6], [0.5, 12.3]], ["A", "A"])
    assert column_decimals(t, 0) == 6 and column_decimals(t, 1) == 1
    assert cell_texts(t)[0] == ["0.000123 ± 0.000012", "45.6 ± 4.6"]
    fixed = Table("t", "T", ("Model",), [Column("p", decimals=3)], [Row("", "x", [13.9671])])
    assert cell_texts(fixed) == [["13.967"]]


def test_missing_cells_are_dashes_and_listed():
    t = _table([[1.0, None], [None, None]], ["A", "A"])
    assert cell_texts(t)[1] == ["—", "—"]
    assert missing_cells(t) == ["A r0: c1", "A r1 (all columns)"]
    assert missing_cells(t, ignore=["c1"]) == ["A r1 (all columns)"]
