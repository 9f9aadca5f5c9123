"""Markdown and terminal (rich) renderings of a ``layout.Table``.

Marks: **bold** = the column's best, significantly better than every other
row; **bold**≈ = tied for best (not significantly different from the lowest
mean); † = does not beat the better image-blind reference; ‡ after a label =
the model ignores its input. A legend under each table says so, with the
test and alpha; the terminal rendering uses bold and dim text.
"""

from __future__ import annotations

from rich.table import Table as RichTable
from rich.text import Text

from .stats import ALPHA
from .table_model import IGNORES, MISSING, NOSKILL, TIE, Table, cell_texts, marks, row_label


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _md_cell(text: str, mark: set[str]) -> str:
    if text == MISSING:
        return text
    text = _md_escape(text)
    if mark & {"best", "tie"}:
        text = f"**{text}**"
    if "tie" in mark:
        text += TIE
    if "noskill" in mark:
        text += f" {NOSKILL}"
    return text


def legend_parts(table: Table, bold: str) -> list[str]:
    """The legend's items with ``bold`` as the example of bold text (format-specific)."""
    parts = []
    if table.judged:
        parts += [f"{bold} = best of its column, significantly better than every other network row (paired t test, "
                  f"Holm-adjusted p < {ALPHA:g}; the image-blind references are judged by {NOSKILL} alone)",
                  f"{bold}{TIE} = tied for best: not significantly different from the row with the lowest mean",
                  f"{NOSKILL} = does not beat the better image-blind reference (the interval of its paired "
                  f"comparison with that reference on the shared test units does not lie above 0; a row with "
                  f"logged means only: its interval does not lie below the reference's mean)"]
        if any("ignores" in r.flags for r in table.rows):
            parts.append(f"{IGNORES} = ignores its input (prediction std < 5% of the ground truth's)")
    parts.append(f"{MISSING} = no FINISHED run (see warnings)")
    return parts


def legend(table: Table) -> str:
    return "Legend: " + "; ".join(legend_parts(table, "**bold**")) + "."


def label_cells(table: Table) -> list[list[str]]:
    """The label columns of each row: the group name on a group's first row only."""
    out, previous = [], None
    for row in table.rows:
        if table.grouped:
            out.append([row.group if row.group != previous else "", row_label(row)])
            previous = row.group
        else:
            out.append([row_label(row)])
    return out


def run_lines(table: Table) -> list[str]:
    """'name: id, id' for every row that has runs."""
    return [f"{row.name}: {', '.join(row.runs)}" for row in table.rows if row.runs]


def to_markdown(table: Table) -> str:
    texts, mk = cell_texts(table), marks(table)
    head = list(table.headers) + [c.heading for c in table.columns]
    lines = [f"### {table.title}", "", "| " + " | ".join(map(_md_escape, head)) + " |",
             "|" + ":---|" * len(table.headers) + "---:|" * len(table.columns)]
    for labels, row_texts, row_marks in zip(label_cells(table), texts, mk):
        cells = [_md_escape(x) for x in labels] + [_md_cell(t, m) for t, m in zip(row_texts, row_marks)]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", table.caption, "", legend(table)]
    runs = run_lines(table)
    if runs:
        lines += ["", "Runs (MLflow run ids): " + "; ".join(runs) + "."]
    for w in table.warnings:
        lines += ["", f"> **Warning:** {w}"]
    return "\n".join(lines) + "\n"


def to_rich(table: Table):
    """A rich Table: bold best, bold + ≈ tied group, dim + † no better than the reference."""
    texts, mk = cell_texts(table), marks(table)
    out = RichTable(title=table.title, caption=table.caption, caption_justify="left", title_justify="left")
    for h in table.headers:
        out.add_column(h)
    for c in table.columns:
        out.add_column(c.heading, justify="right")
    for i, (labels, row_texts, row_marks) in enumerate(zip(label_cells(table), texts, mk)):
        cells = [Text(x) for x in labels]
        for t, m in zip(row_texts, row_marks):
            style = " ".join(s for s, on in (("bold", bool(m & {"best", "tie"})), ("dim", "noskill" in m)) if on)
            suffix = (TIE if "tie" in m else "") + (f" {NOSKILL}" if "noskill" in m else "")
            cells.append(Text(t + suffix, style=style))
        end = table.grouped and i + 1 < len(table.rows) and table.rows[i + 1].group != table.rows[i].group
        out.add_row(*cells, end_section=end)
    return out
