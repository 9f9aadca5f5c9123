"""Number formatting, stored marks and their rendering in Markdown and LaTeX, on hand-made tables."""

from __future__ import annotations

from bronchocli.reporting.latex import to_latex
from bronchocli.reporting.markdown import to_markdown
from bronchocli.reporting.table_model import (
    Column,
    Estimate,
    Row,
    Table,
    cell_texts,
    column_decimals,
    marks,
    missing_cells,
)


def _table(values, groups, mk=None, highlight=True) -> Table:
    rows = [Row(g, f"r{i}", [None if v is None else Estimate(v, v * 0.9, v * 1.1) for v in vals])
            for i, (g, vals) in enumerate(zip(groups, values))]
    cols = [Column(f"c{j}", highlight=highlight) for j in range(len(values[0]))]
    return Table("t", "T", ("Network", "Loss"), cols, rows, marks=mk, judged=mk is not None)


def test_decimals_follow_the_smallest_mean_of_the_column_and_bounds_share_them():
    t = _table([[0.000123, 45.6], [0.5, 12.3]], ["A", "A"])
    assert column_decimals(t, 0) == 6 and column_decimals(t, 1) == 1
    assert cell_texts(t)[0] == ["0.000123 [0.000111, 0.000135]", "45.6 [41.0, 50.2]"]
    fixed = Table("t", "T", ("Model",), [Column("p", decimals=3)], [Row("", "x", [13.9671])])
    assert cell_texts(fixed) == [["13.967"]]
    assert cell_texts(Table("t", "T", ("Model",), [Column("e")], [Row("", "x", [Estimate(2.0)])])) == [["2.00"]]


def test_without_builder_marks_nothing_is_marked():
    t = _table([[1.0], [2.0]], ["A", "A"])
    assert marks(t) == [[set()], [set()]]


def test_marks_render_as_bold_tie_and_dagger():
    t = _table([[1.0], [1.01], [3.0]], ["A", "A", "B"], mk=[[{"tie"}], [{"tie"}], [{"noskill"}]])
    t.rows[2].flags = {"ignores"}
    md = to_markdown(t)
    assert "| A | r0 | **1.00 [0.90, 1.10]**≈ |" in md
    assert "|  | r1 | **1.01 [0.91, 1.11]**≈ |" in md
    assert "| B | r2 ‡ | 3.00 [2.70, 3.30] † |" in md
    assert "**Bold**≈: tied for best" in md and "‡: the model ignores its input" in md
    assert "**Bold**: " not in md  # no single best in this table: no footnote for it
    tex = to_latex(t)
    assert r"\textbf{1.00 [0.90, 1.10]}\ensuremath{\approx}" in tex
    assert r"r2 \ensuremath{^\ddagger} & 3.00 [2.70, 3.30]\ensuremath{^\dagger}" in tex
    best = _table([[1.0], [2.0]], ["A", "A"], mk=[[{"best"}], [set()]])
    assert "| A | r0 | **1.00 [0.90, 1.10]** |" in to_markdown(best)


def test_missing_cells_are_dashes_and_listed_for_model_rows_only():
    t = _table([[1.0, None], [None, None]], ["A", "A"])
    t.rows.append(Row("Image-blind", "Zero motion", [None, None], kind="reference"))
    assert cell_texts(t)[1] == ["—", "—"]
    assert missing_cells(t) == ["A r0: c1", "A r1 (all columns)"]
    assert missing_cells(t, ignore=["c1"]) == ["A r1 (all columns)"]
