"""The Methods page (issue 57.4): `report` writes methods.md and methods.tex beside the tables; every caption's
"as in Methods" names that page, a file that exists; the page states the code's own definitions and constants."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest
from report_fakes import golden_tables

from bronchocli import registry
from bronchocli.reporting import methods, stats
from bronchocli.reporting.captions import METHODS
from bronchocli.reporting.judge import IGNORES_RATIO
from bronchocli.reporting.report import write_tables

LINK = re.compile(r"as in \[Methods\]\(([^)\s]+)\)")  # Markdown: a link to the page
NAMED = re.compile(r"as in Methods \(([^)\s]+)\)")  # LaTeX: the page named


@pytest.fixture(scope="module")
def written(golden_store, tmp_path_factory):
    tables = list(golden_tables(golden_store)[0].values())
    out = tmp_path_factory.mktemp("report")
    files = write_tables(tables, out, ("md", "tex"))
    return tables, out, files


def test_the_report_writes_the_methods_page_in_each_format_it_writes(written, tmp_path):
    tables, out, files = written
    assert {out / "methods.md", out / "methods.tex"} <= set(files)
    assert (out / "methods.md").read_text().startswith("# Methods\n")
    assert r"\section{Methods}\label{sec:methods}" in (out / "methods.tex").read_text()
    assert write_tables(tables[:1], tmp_path, ("md",))[-1] == tmp_path / "methods.md"  # only the formats written
    assert not (tmp_path / "methods.tex").exists()
    assert write_tables([], tmp_path / "none", ("md",)) == []  # no table: no page of what no table shows


def test_every_captions_pointer_names_a_file_that_exists(written):
    tables, out, _ = written
    assert all(METHODS in t.caption for t in tables)  # the caption itself keeps the plain phrase (no file name)
    for t in tables:
        md, tex = (out / f"{t.key}.md").read_text(), (out / f"{t.key}.tex").read_text()
        targets = LINK.findall(md) + NAMED.findall(tex)
        assert len(targets) == 2, (t.key, targets)
        for target in targets:
            assert (out / target).is_file(), (t.key, target)


def test_the_page_states_the_codes_definitions():
    text = methods.to_markdown()
    specs = registry.metric_specs(per="pose", table="paper")
    assert [s.label for s in specs] == ["Position L2", "Rotation L2", "DE", "CE"]  # the paper's four, per pair
    for spec in specs:  # each metric's row: its label, the definition its function's docstring gives, its unit
        assert f"| {spec.label} | {methods.definition(spec)} | {spec.symbol or spec.unit} |" in text
        assert len(methods.definition(spec)) > 40  # a definition, not the label again
    assert "wrapped into (-180°, 180°]" in text and "arccos" in text and "1 − cos" in text
    assert f"α = {stats.ALPHA:g}" in text and f"{100 * stats.LEVEL:g} % interval" in text
    assert f"fewer than {stats.MIN_SEEDS} seeds" in text and f"fewer than {stats.MIN_PATIENTS} patients" in text
    assert f"{100 * IGNORES_RATIO:g} % of the ground truth's" in text
    assert "Zero motion" in text and "Training mean" in text and "Skill = 1 − error ÷" in text
    assert "population standard deviation (divisor n)" in text  # what metrics.Stat computes (ddof 0)
    assert "Per pair" in text and "Accumulated" in text and "†" in text and "Holm" in text


def test_a_metric_without_a_docstring_is_defined_by_its_label_and_unit():
    spec = registry.MetricSpec("toy", lambda pred, gt: pred, "pose", "voxels", "Toy L1", "vox")
    assert methods.definition(spec) == "Toy L1 (voxels)"


@pytest.mark.heavy
@pytest.mark.skipif(shutil.which("pdflatex") is None, reason="no pdflatex (Debian: texlive-latex-base)")
def test_the_latex_methods_page_compiles(tmp_path):
    (tmp_path / "methods.tex").write_text(methods.to_latex(), encoding="utf-8")
    done = subprocess.run(["pdflatex", "-interaction=nonstopmode", "-halt-on-error", "methods.tex"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, (tmp_path / "methods.log").read_text(encoding="latin-1")[-3000:]
