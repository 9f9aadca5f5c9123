"""LaTeX rendering of a ``layout.Table``: a standalone document that compiles with pdflatex.

The document needs only packages of Debian's texlive-latex-base and
texlive-latex-recommended (booktabs, xcolor, geometry), on a landscape A4 page
(the widest table, Table 9 with its intervals, is ~27 cm: wider than a portrait
page's text, pdflatex reported it overfull). The ``table``
environment between the ``% --- table`` markers can be pasted into a paper that
loads booktabs and threeparttable: the caption heads the table, the footnotes
of the marks it uses are its ``tablenotes`` (where threeparttable is not
installed the document defines the two environments itself). The source and
run ids follow the float, outside the markers. Marks: \\textbf = the column's significant best; \\textbf with
$\\approx$ = tied for best; $\\dagger$ = does not beat the better image-blind
reference; $\\ddagger$ after a label = ignores its input. Warnings go into the
file as comments.
"""

from __future__ import annotations

from .captions import methods_pointer
from .markdown import label_cells, note_lines, run_lines
from .table_model import MISSING, Table, cell_texts, marks

_SPECIAL = {
    "\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
    "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}",
}
_UNICODE = {
    "±": r"\ensuremath{\pm}", "°": r"\ensuremath{^\circ}", "—": "---", "–": "--", "−": r"\ensuremath{-}",
    "σ": r"\ensuremath{\sigma}", "μ": r"\ensuremath{\mu}", "Σ": r"\ensuremath{\Sigma}", "²": r"\ensuremath{^{2}}",
    "×": r"\ensuremath{\times}", "†": r"\ensuremath{^\dagger}", "‡": r"\ensuremath{^\ddagger}",
    "≈": r"\ensuremath{\approx}", "≥": r"\ensuremath{\geq}", "≤": r"\ensuremath{\leq}", "·": r"\ensuremath{\cdot}",
    "Δ": r"\ensuremath{\Delta}", "α": r"\ensuremath{\alpha}", "β": r"\ensuremath{\beta}", "γ": r"\ensuremath{\gamma}",
    "÷": r"\ensuremath{\div}", "’": "'", "‘": "`", "“": "``", "”": "''",
}

PREAMBLE = r"""\documentclass{article}
\usepackage[utf8]{inputenc}
\usepackage[a4paper,landscape,margin=1cm]{geometry}
\usepackage{booktabs}
\usepackage{xcolor}
\IfFileExists{threeparttable.sty}{\usepackage{threeparttable}}{%
  \newenvironment{threeparttable}{\begin{minipage}{\linewidth}\centering}{\end{minipage}}%
  \newenvironment{tablenotes}[1][]{\par\smallskip\begin{list}{}{\setlength{\leftmargin}{0pt}%
    \setlength{\itemsep}{0pt}\setlength{\parsep}{0pt}\raggedright}}{\end{list}}}
\pagestyle{empty}
\begin{document}
"""


def escape(text: str) -> str:
    """Plain text -> LaTeX text (special characters escaped, known non-ASCII symbols as commands)."""
    return "".join(_SPECIAL.get(ch) or _UNICODE.get(ch) or ch for ch in text)


def _cell(text: str, mark: set[str]) -> str:
    out = escape(text)
    if text == MISSING:
        return out
    if mark & {"best", "tie"}:
        out = rf"\textbf{{{out}}}"
    if "tie" in mark:
        out += escape("≈")
    if "noskill" in mark:
        out += escape("†")
    return out


def _notes(table: Table) -> list[str]:
    bold = escape("**Bold**")
    return [r"\item[] " + escape(n).replace(bold, r"\textbf{Bold}") for n in note_lines(table)]


def _body(table: Table) -> list[str]:
    texts, mk = cell_texts(table), marks(table)
    lines = []
    for i, (labels, row_texts, row_marks) in enumerate(zip(label_cells(table), texts, mk)):
        if i > 0 and ((table.grouped and labels[0]) or (table.rows[i].kind != table.rows[i - 1].kind)):
            lines.append(r"\midrule")
        cells = [escape(x) for x in labels] + [_cell(t, m) for t, m in zip(row_texts, row_marks)]
        lines.append(" & ".join(cells) + r" \\")
    return lines


def _runs(table: Table) -> str:
    entries = []
    for line in run_lines(table):
        name, _, ids = line.partition(": ")
        entries.append(escape(name) + ": " + ", ".join(rf"\texttt{{{i}}}" for i in ids.split(", ")))
    return "Runs: " + "; ".join(entries) + "." if entries else ""


def table_environment(table: Table) -> str:
    """The ``table`` float alone (booktabs, threeparttable), ready to paste into a paper."""
    spec = "l" * len(table.headers) + "r" * len(table.columns)
    head = [escape(h) for h in table.headers] + [escape(c.heading) for c in table.columns]
    lines = [r"\begin{table}[ht]", r"\centering", r"\small", r"\setlength{\tabcolsep}{4pt}",
             r"\begin{threeparttable}", rf"\caption{{{methods_pointer(escape(table.caption), 'tex')}}}",
             rf"\label{{tab:{table.key}}}", rf"\begin{{tabular}}{{{spec}}}", r"\toprule",
             " & ".join(head) + r" \\", r"\midrule", *_body(table), r"\bottomrule", r"\end{tabular}"]
    notes = _notes(table)
    if notes:
        lines += [r"\begin{tablenotes}[flushleft]", r"\footnotesize", *notes, r"\end{tablenotes}"]
    lines += [r"\end{threeparttable}", r"\end{table}"]
    return "\n".join(lines)


def _source(table: Table) -> str:
    """The source and run ids, after the float (not part of what a paper prints)."""
    parts = [escape("Source: " + " ".join(table.source))] if table.source else []
    runs = _runs(table)
    if runs:
        parts.append(runs)
    if not parts:
        return ""
    return "\n".join([r"\begin{flushleft}\footnotesize", r"\par ".join(parts), r"\end{flushleft}"]) + "\n"


def to_latex(table: Table) -> str:
    """A standalone document holding ``table_environment(table)``; warnings as comments."""
    head = [f"% {escape(table.title)} -- written by `bronchopose report`; compile with pdflatex.",
            "% Needs booktabs and threeparttable; the table environment between the markers can be pasted into a "
            "paper."]
    head += [f"% warning: {' '.join(w.splitlines())}" for w in table.warnings]
    return "\n".join(head) + "\n" + PREAMBLE + "% --- table begins\n" + table_environment(table) + \
        "\n% --- table ends\n" + _source(table) + "\\end{document}\n"
