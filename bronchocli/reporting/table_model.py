"""The table model every renderer shares: columns, grouped rows, number formatting, marks.

A value cell is an :class:`Estimate` (mean with its 95 % interval), a plain
number (params, latency), a text, or ``None`` (missing: shown as ``—``).
The statistical marks are decided by the table builders (``judge.py``) and
stored on the table; renderers only style them:

* ``best``: the column's best row, significantly better than every other row;
* ``tie``: one of the rows not significantly different from the column's best
  (the tied-best group; no single best is claimed);
* ``noskill``: the row does not beat the better image-blind reference.

A row flag ``ignores`` marks a model whose predictions hardly vary (it ignores
its input). Reference rows (``kind="reference"``) are never ranked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

MISSING = "—"
TIE, NOSKILL, IGNORES = "≈", "†", "‡"
SIGNIFICANT = 3  # significant digits of the column's smallest |mean|; interval bounds share its decimals
MAX_DECIMALS = 8


@dataclass(frozen=True)
class Column:
    title: str
    unit: str = ""  # shown after the title, e.g. "vox"
    highlight: bool = True  # an error column: judged (lower is better)
    decimals: int | None = None  # fixed decimals; None: from the values (SIGNIFICANT digits)

    @property
    def heading(self) -> str:
        return f"{self.title} ({self.unit})" if self.unit else self.title


@dataclass(frozen=True)
class Estimate:
    """A table value: mean and its interval (None: no interval, e.g. a run without per-trajectory errors)."""

    mean: float
    lo: float | None = None
    hi: float | None = None

    @property
    def has_interval(self) -> bool:
        return self.lo is not None and self.hi is not None


Value = Estimate | float | str | None


@dataclass
class Row:
    group: str  # architecture group name ("" when the table has no groups)
    label: str  # e.g. the loss "MSE+CE"
    values: list[Value]
    runs: list[str] = field(default_factory=list)  # MLflow run ids behind the row
    kind: str = "model"  # "model" or "reference" (image-blind; never ranked)
    flags: set[str] = field(default_factory=set)  # {"ignores"}
    info: dict[str, Any] = field(default_factory=dict)  # what the builder knows (n, samples), not rendered
    model: str = ""  # a model row: the model's one name (registry.model_name), which its labels show

    @property
    def name(self) -> str:
        """The row's name in notes, run lists and figures: the model's name, else its labels."""
        return self.model or f"{self.group} {self.label}".strip()


@dataclass
class Table:
    key: str  # file stem, e.g. "table2-personalized-accumulated"
    title: str  # e.g. "Table 2. Personalized, accumulated evaluation"
    headers: tuple[str, ...]  # headings of the label columns: ("Network", "Loss") or ("Model",)
    columns: list[Column]
    rows: list[Row]
    caption: str = ""  # at most three sentences: what is compared, the estimand in words, n (captions.py)
    notes: list[str] = field(default_factory=list)  # notes that apply (means-only rows, definitions), after the marks'
    source: list[str] = field(default_factory=list)  # where the numbers come from: sweep, seeds, budget, numerics
    warnings: list[str] = field(default_factory=list)
    marks: list[list[set[str]]] | None = None  # rows x columns, from the builder
    skill: dict[str, dict[str, Any]] = field(default_factory=dict)  # row name -> metric -> stats.Derived
    judged: bool = False  # the statistical marks apply

    @property
    def grouped(self) -> bool:
        return len(self.headers) == 2

    def frame(self):
        """The table as a pandas DataFrame: one row per table row (the label columns, then per value column its
        mean and, where it has one, the interval's ``lo``/``hi``, then ``kind`` and the marks as text: ``best``,
        ``tie`` or ``noskill`` per column), in the table's order. Numbers unrounded, as the runs gave them."""
        import pandas as pd  # lazy: only a caller who asks for a DataFrame pays for pandas

        grid = marks(self)
        records = []
        for i, row in enumerate(self.rows):
            rec: dict[str, Any] = {}
            if self.grouped:
                rec[self.headers[0]], rec[self.headers[1]] = row.group, row.label
            else:
                rec[self.headers[0]] = row.label
            for j, col in enumerate(self.columns):
                v = row.values[j]
                rec[col.heading] = v if isinstance(v, str) else center(v)
                if isinstance(v, Estimate) and v.has_interval:
                    rec[f"{col.heading} lo"], rec[f"{col.heading} hi"] = v.lo, v.hi
                rec[f"{col.heading} marks"] = " ".join(sorted(grid[i][j]))
            rec["kind"] = row.kind
            records.append(rec)
        return pd.DataFrame.from_records(records)

    def groups(self) -> list[tuple[str, list[int]]]:
        """Consecutive rows sharing a group, as (group, row indices)."""
        out: list[tuple[str, list[int]]] = []
        for i, row in enumerate(self.rows):
            if out and out[-1][0] == row.group:
                out[-1][1].append(i)
            else:
                out.append((row.group, [i]))
        return out


def center(value: Value) -> float | None:
    if value is None or isinstance(value, str):
        return None
    v = value.mean if isinstance(value, Estimate) else float(value)
    return None if math.isnan(v) else v


def column_decimals(table: Table, j: int) -> int:
    col = table.columns[j]
    if col.decimals is not None:
        return col.decimals
    values = [abs(v) for r in table.rows if (v := center(r.values[j])) is not None and v != 0]
    if not values:
        return 2
    return max(0, min(MAX_DECIMALS, SIGNIFICANT - 1 - math.floor(math.log10(min(values)))))


def format_value(value: Value, decimals: int) -> str:
    if isinstance(value, str):
        return value
    if center(value) is None:
        return MISSING
    if isinstance(value, Estimate):
        text = f"{value.mean:.{decimals}f}"
        if value.has_interval:
            text += f" [{value.lo:.{decimals}f}, {value.hi:.{decimals}f}]"
        return text
    return f"{float(value):.{decimals}f}"  # type: ignore[arg-type]


def cell_texts(table: Table) -> list[list[str]]:
    """Every value cell as plain text (``MISSING`` for no value), rows x columns."""
    decimals = [column_decimals(table, j) for j in range(len(table.columns))]
    return [[format_value(v, decimals[j]) for j, v in enumerate(row.values)] for row in table.rows]


def marks(table: Table) -> list[list[set[str]]]:
    """The builder's marks per cell (rows x columns); empty sets when it set none."""
    if table.marks is not None:
        return table.marks
    return [[set() for _ in table.columns] for _ in table.rows]


def row_label(row: Row) -> str:
    return row.label + (f" {IGNORES}" if "ignores" in row.flags else "")


def missing_cells(table: Table, ignore: Sequence[str] = ()) -> list[str]:
    """Model rows with empty value cells: 'name (all columns)' or 'name: col, col' (``ignore``: headings)."""
    out = []
    for row in table.rows:
        if row.kind != "model":
            continue
        empty = [col.heading for col, v in zip(table.columns, row.values)
                 if center(v) is None and not isinstance(v, str) and col.heading not in ignore]
        if empty and len(empty) == sum(col.heading not in ignore for col in table.columns):
            out.append(f"{row.name} (all columns)")
        elif empty:
            out.append(f"{row.name}: {', '.join(empty)}")
    return out
