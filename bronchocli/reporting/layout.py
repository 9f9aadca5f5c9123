"""The table model every renderer shares: columns, grouped rows, number formatting, highlighting.

Highlighting follows the paper. Within a column marked ``highlight`` (the
error metrics; lower is better for all of them):

* ``group``: best value of its architecture group (bold), only where the group
  has at least two values in that column;
* ``best``: best value of the whole column (red), ``second``: the next best
  distinct value (blue), only where the column has at least two values.

Values are ranked as displayed (after rounding to the column's decimals), so
cells that print the same number get the same mark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

from ..metrics import Stat

MISSING = "—"
SIGNIFICANT = 3  # significant digits of the column's smallest |mean|; mean and std share its decimals
MAX_DECIMALS = 8


@dataclass(frozen=True)
class Column:
    title: str
    unit: str = ""  # shown after the title, e.g. "vox"
    highlight: bool = True  # rank this column (lower is better)
    decimals: int | None = None  # fixed decimals; None: from the values (SIGNIFICANT digits)

    @property
    def heading(self) -> str:
        return f"{self.title} ({self.unit})" if self.unit else self.title


Value = Stat | float | None  # Stat: "mean ± std"; float: a plain number; None: missing


@dataclass
class Row:
    group: str  # architecture group name ("" when the table has no groups)
    label: str  # e.g. the loss "MSE+CE"
    values: list[Value]
    runs: list[str] = field(default_factory=list)  # MLflow run ids behind the row


@dataclass
class Table:
    key: str  # file stem, e.g. "table2-personalized-accumulated"
    title: str  # e.g. "Table 2. Personalized, accumulated evaluation"
    headers: tuple[str, ...]  # headings of the label columns: ("Network", "Loss") or ("Model",)
    columns: list[Column]
    rows: list[Row]
    caption: str = ""
    warnings: list[str] = field(default_factory=list)

    @property
    def grouped(self) -> bool:
        return len(self.headers) == 2

    def groups(self) -> list[tuple[str, list[int]]]:
        """Consecutive rows sharing a group, as (group, row indices)."""
        out: list[tuple[str, list[int]]] = []
        for i, row in enumerate(self.rows):
            if out and out[-1][0] == row.group:
                out[-1][1].append(i)
            else:
                out.append((row.group, [i]))
        return out


def _center(value: Value) -> float | None:
    if value is None:
        return None
    v = value.mean if isinstance(value, Stat) else float(value)
    return None if math.isnan(v) else v


def column_decimals(table: Table, j: int) -> int:
    col = table.columns[j]
    if col.decimals is not None:
        return col.decimals
    values = [abs(v) for r in table.rows if (v := _center(r.values[j])) is not None and v != 0]
    if not values:
        return 2
    return max(0, min(MAX_DECIMALS, SIGNIFICANT - 1 - math.floor(math.log10(min(values)))))


def format_value(value: Value, decimals: int, pm: str = "±") -> str:
    if _center(value) is None:
        return MISSING
    if isinstance(value, Stat):
        return f"{value.mean:.{decimals}f} {pm} {value.std:.{decimals}f}"
    return f"{float(value):.{decimals}f}"


def cell_texts(table: Table, pm: str = "±") -> list[list[str]]:
    """Every value cell as plain text (``MISSING`` for no value), rows x columns."""
    decimals = [column_decimals(table, j) for j in range(len(table.columns))]
    return [[format_value(v, decimals[j], pm) for j, v in enumerate(row.values)] for row in table.rows]


def _ranked(table: Table, j: int, rows: Sequence[int], decimals: int) -> list[tuple[float, int]]:
    out = []
    for i in rows:
        v = _center(table.rows[i].values[j])
        if v is not None:
            out.append((round(v, decimals), i))
    return sorted(out)


def marks(table: Table) -> list[list[set[str]]]:
    """Highlight marks per cell (rows x columns): subsets of {"group", "best", "second"}."""
    out: list[list[set[str]]] = [[set() for _ in table.columns] for _ in table.rows]
    every = list(range(len(table.rows)))
    for j, col in enumerate(table.columns):
        if not col.highlight:
            continue
        d = column_decimals(table, j)
        ranked = _ranked(table, j, every, d)
        distinct = sorted({v for v, _ in ranked})
        if len(ranked) >= 2:
            for v, i in ranked:
                if v == distinct[0]:
                    out[i][j].add("best")
                elif len(distinct) > 1 and v == distinct[1]:
                    out[i][j].add("second")
        if table.grouped:
            for _, rows in table.groups():
                in_group = _ranked(table, j, rows, d)
                if len(in_group) >= 2:
                    for v, i in in_group:
                        if v == in_group[0][0]:
                            out[i][j].add("group")
    return out


def missing_cells(table: Table, ignore: Sequence[str] = ()) -> list[str]:
    """Rows with empty value cells: 'group label (all columns)' or 'group label: col, col' (``ignore``: headings)."""
    out = []
    for row in table.rows:
        name = f"{row.group} {row.label}".strip()
        empty = [col.heading for col, v in zip(table.columns, row.values)
                 if _center(v) is None and col.heading not in ignore]
        if empty and len(empty) == sum(col.heading not in ignore for col in table.columns):
            out.append(f"{name} (all columns)")
        elif empty:
            out.append(f"{name}: {', '.join(empty)}")
    return out
