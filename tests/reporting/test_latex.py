"""The LaTeX tables are well-formed (a syntax check that always runs) and compile with pdflatex (when installed)."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest
from report_fakes import PROFILES, frames_runs

from bronchocli.reporting import report, tables
from bronchocli.reporting.figures import errors_loader
from bronchocli.reporting.latex import escape, to_latex
from bronchocli.reporting.table_model import Column, Estimate, Row, Table


def _strip_comments(text: str) -> str:
    return "\n".join(re.sub(r"(?<!\\)%.*", "", line) for line in text.splitlines())


def _braces(text: str) -> list[str]:
    depth = 0
    for i, ch in enumerate(re.sub(r"\\[{}]", "", text)):
        depth += {"{": 1, "}": -1}.get(ch, 0)
        if depth < 0:
            return [f"unbalanced '}}' near character {i}"]
    return [] if depth == 0 else [f"{depth} unclosed '{{'"]


def _environments(text: str) -> list[str]:
    stack, problems = [], []
    for kind, name in re.findall(r"\\(begin|end)\{([^}]*)\}", text):
        if kind == "begin":
            stack.append(name)
        elif not stack or stack.pop() != name:
            problems.append(f"\\end{{{name}}} does not close the open environment")
    return problems + [f"\\begin{{{n}}} never closed" for n in stack]


def _tabular_rows(text: str) -> list[str]:
    problems = []
    for spec, body in re.findall(r"\\begin\{tabular\}\{([^}]*)\}(.*?)\\end\{tabular\}", text, flags=re.S):
        ncols = len(re.findall(r"[lrcp]", spec))
        for row in re.split(r"\\\\", body):
            row = re.sub(r"\\(toprule|midrule|bottomrule)", "", row).strip()
            cells = len(re.findall(r"(?<!\\)&", row)) + 1
            if row and cells != ncols:
                problems.append(f"row with {cells} cells, spec has {ncols}: {row[:60]}")
    return problems


def _specials(body: str) -> list[str]:
    """Specials that must be escaped anywhere (math snippets already removed), and '&' outside tabulars."""
    problems = [f"unescaped '{m.group(1)}'" for m in re.finditer(r"(?<!\\)([#_^~$])", body)]
    outside = re.sub(r"\\begin\{tabular\}.*?\\end\{tabular\}", "", body, flags=re.S)
    return problems + ["unescaped '&' outside a tabular" for _ in re.finditer(r"(?<!\\)&", outside)]


def latex_problems(text: str) -> list[str]:
    """Syntax-level problems of a generated document: braces, environments, column counts, specials, non-ASCII."""
    body = _strip_comments(text)
    body = re.sub(r"\\ensuremath\{[^{}]*(\{[^{}]*\})?[^{}]*\}", "M", body)  # math snippets are fine
    problems = _braces(_strip_comments(text)) + _environments(body) + _tabular_rows(body) + _specials(body)
    problems += [f"non-ASCII character {ch!r}" for ch in sorted(set(_strip_comments(text))) if ord(ch) > 127]
    if not re.search(r"\\documentclass.*\\begin\{document\}.*\\end\{document\}", body, flags=re.S):
        problems.append("not a complete document")
    return problems


@pytest.mark.parametrize("bad, problem", [
    (r"\begin{document}x{\end{document}", "unclosed"),
    (r"\begin{document}\begin{table}\end{document}", "does not close"),
    (r"\begin{document}\begin{tabular}{lr}a & b & c \\ \end{tabular}\end{document}", "row with 3 cells"),
    (r"\begin{document}a_b\end{document}", "unescaped '_'"),
    ("\\begin{document}caf\u00e9\\end{document}", "non-ASCII"),
])
def test_the_checker_catches_broken_latex(bad, problem):
    assert any(problem in p for p in latex_problems(r"\documentclass{article}" + bad))


@pytest.fixture(scope="module")
def documents(golden_store) -> dict[str, str]:
    g = golden_store
    ctx = tables.ReportContext(report.collect_index(g.client, g.cfg), profiler=PROFILES.get,
                               errors=errors_loader(g.client))
    built = report.build_tables(ctx, list(tables.TABLES), ["accumulated", "pair"])
    built += report.build_tables(frames_runs().context(), ["frames"], ["accumulated", "pair"])
    docs = {t.key: to_latex(t) for t in built}
    assert {"table2-personalized-accumulated", "table8-frames-pair"} <= docs.keys()
    docs["hostile"] = to_latex(_hostile_table())
    return docs


def _hostile_table() -> Table:
    """Every special character LaTeX has, in titles, labels, headings and caption."""
    nasty = r"a_b & c% d#e $f ^g ~h {i} \j σ² ± — ° × ≈ ≥ † ‡"
    return Table("hostile", nasty, ("Net_work", "Lo&ss"), [Column("C#1", "100%"), Column("x_y", "°")],
                 [Row("G_1", "MSE+CE", [Estimate(1.0, 0.5, 3), None], flags={"ignores"}),
                  Row("G_1", "a&b", [Estimate(2.0, 0.1, 3), 3.5]), Row("R", "ref", ["", nasty], kind="reference")],
                 caption=nasty, warnings=["line\nbreak % in a warning"], judged=True,
                 marks=[[{"best"}, set()], [{"tie", "noskill"}, set()], [set(), set()]])


def test_every_generated_document_passes_the_syntax_check(documents):
    for key, text in documents.items():
        assert latex_problems(text) == [], key


def test_escape_covers_specials_and_symbols():
    assert escape("a_b&c%d#e$f{g}") == r"a\_b\&c\%d\#e\$f\{g\}"
    assert escape("~^\\") == r"\textasciitilde{}\textasciicircum{}\textbackslash{}"
    assert escape("± — °") == r"\ensuremath{\pm} --- \ensuremath{^\circ}"
    assert escape("≈ ≥ ×") == r"\ensuremath{\approx} \ensuremath{\geq} \ensuremath{\times}"


@pytest.mark.skipif(shutil.which("pdflatex") is None, reason="pdflatex not installed (texlive-latex-recommended)")
def test_documents_compile_with_pdflatex(documents, tmp_path):
    for key, text in documents.items():
        (tmp_path / f"{key}.tex").write_text(text, encoding="utf-8")
        result = subprocess.run(["pdflatex", "-interaction=nonstopmode", "-halt-on-error", f"{key}.tex"],
                                cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert result.returncode == 0, f"{key}: {result.stdout[-2000:]}"
        assert (tmp_path / f"{key}.pdf").stat().st_size > 1000
