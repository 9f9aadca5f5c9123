"""Markdown and terminal (rich) renderings of a ``layout.Table``.

Marks: **bold** = the column's best, significantly better than every other
row; **bold**≈ = tied for best (not significantly different from the lowest
mean); † = does not beat the better image-blind reference; ‡ after a label =
the model ignores its input. The caption comes before the table, a footnote for
each mark the table uses after it (captions.py), then its source and run ids;
the terminal rendering uses bold and dim text.
"""

from __future__ import annotations

from rich.table import Table as RichTable
from rich.text import Text

from .captions import footnotes, methods_pointer
from .table_model import MISSING, NOSKILL, TIE, Table, cell_texts, marks, row_label


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


def note_lines(table: Table, bold: str = "**Bold**") -> list[str]:
    """The footnotes (captions.footnotes) as lines: "**Bold**: significantly better …", "†: …", or the note alone;
    ``bold``: the format's bold example."""
    out = []
    for mark, text in footnotes(table):
        label = {"bold": bold, f"bold{TIE}": f"{bold}{TIE}"}.get(mark, mark)
        out.append(f"{label}: {text}" if label else text)
    return out


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
    lines = [f"### {table.title}", ""] + ([methods_pointer(table.caption, "md"), ""] if table.caption else [])
    lines += ["| " + " | ".join(map(_md_escape, head)) + " |",
             "|" + ":---|" * len(table.headers) + "---:|" * len(table.columns)]
    for labels, row_texts, row_marks in zip(label_cells(table), texts, mk):
        cells = [_md_escape(x) for x in labels] + [_md_cell(t, m) for t, m in zip(row_texts, row_marks)]
        lines.append("| " + " | ".join(cells) + " |")
    for note in note_lines(table):
        lines += ["", note]
    if table.source:
        lines += ["", "Source: " + " ".join(table.source)]
    runs = run_lines(table)
    if runs:
        lines += ["", "Runs (MLflow run ids): " + "; ".join(runs) + "."]
    for w in table.warnings:
        lines += ["", f"> **Warning:** {w}"]
    return "\n".join(lines) + "\n"


def to_rich(table: Table):
    """A rich Table: bold best, bold + ≈ tied group, dim + † no better than the reference."""
    texts, mk = cell_texts(table), marks(table)
    text = "\n".join([methods_pointer(table.caption, "text")] + note_lines(table, "bold"))
    out = RichTable(title=table.title, caption=text, caption_justify="left", title_justify="left")
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
