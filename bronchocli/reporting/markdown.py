"""Markdown and terminal (rich) renderings of a ``model.Table``.

Markdown has no colours, so the paper's marks become: **bold** = best of its
architecture group, _italic_ with † = best of the column (red in LaTeX and on
the terminal), _italic_ with ‡ = second best (blue). A legend under each table
says so. The terminal rendering uses real bold/red/blue.
"""

from __future__ import annotations

from rich.table import Table as RichTable
from rich.text import Text

from .layout import MISSING, Table, cell_texts, marks

BEST, SECOND = "†", "‡"


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _md_cell(text: str, mark: set[str]) -> str:
    if text == MISSING:
        return text
    if mark & {"best", "second"}:
        text = f"_{text}_"
    if "group" in mark:
        text = f"**{text}**"
    if "best" in mark:
        text += BEST
    elif "second" in mark:
        text += SECOND
    return text


def legend(table: Table) -> str:
    parts = []
    if table.grouped:
        parts.append("**bold** = best of its architecture group")
    if any(c.highlight for c in table.columns):
        parts += [f"_italic_{BEST} = best of the column (red in LaTeX)",
                  f"_italic_{SECOND} = second best (blue in LaTeX)"]
    parts.append(f"{MISSING} = no FINISHED run (see warnings)")
    return "Legend: " + "; ".join(parts) + "."


def label_cells(table: Table) -> list[list[str]]:
    """The label columns of each row: the group name on a group's first row only."""
    out, previous = [], None
    for row in table.rows:
        if table.grouped:
            out.append([row.group if row.group != previous else "", row.label])
            previous = row.group
        else:
            out.append([row.label])
    return out


def run_lines(table: Table) -> list[str]:
    """'name: id, id' for every row that has runs."""
    out = []
    for row in table.rows:
        if row.runs:
            name = f"{row.group} {row.label}".strip()
            out.append(f"{name}: {', '.join(row.runs)}")
    return out


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
        lines += ["", "Runs (MLflow run ids): " + "; ".join(f"{r}" for r in runs) + "."]
    for w in table.warnings:
        lines += ["", f"> **Warning:** {w}"]
    return "\n".join(lines) + "\n"


def to_rich(table: Table):
    """A rich Table with the paper's marks in colour (red best, blue second, bold group best)."""
    texts, mk = cell_texts(table), marks(table)
    out = RichTable(title=table.title, caption=table.caption, caption_justify="left", title_justify="left")
    for h in table.headers:
        out.add_column(h)
    for c in table.columns:
        out.add_column(c.heading, justify="right")
    for i, (labels, row_texts, row_marks) in enumerate(zip(label_cells(table), texts, mk)):
        cells = [Text(x) for x in labels]
        for t, m in zip(row_texts, row_marks):
            style = " ".join(s for s, on in (("bold", "group" in m), ("red", "best" in m),
                                             ("blue", "second" in m)) if on)
            cells.append(Text(t, style=style))
        end = table.grouped and i + 1 < len(table.rows) and table.rows[i + 1].group != table.rows[i].group
        out.add_row(*cells, end_section=end)
    return out
