"""Golden files: the exact Markdown and LaTeX of every table from a fabricated sweep (real MLflow store).

Run ids are random, so they are replaced by ``<label>`` before comparing. To
regenerate after an intended change: ``BRONCHO_UPDATE_GOLDEN=1 pytest
tests/reporting/test_golden.py`` and review the diff of tests/reporting/golden/.
The explicit assertions below pin the highlighting independently of the files.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from report_fakes import EXPERIMENT, PROFILES, SWEEP

from bronchocli.reporting import collect, tables
from bronchocli.reporting.latex import to_latex
from bronchocli.reporting.markdown import to_markdown

GOLDEN = Path(__file__).parent / "golden"
UPDATE = os.environ.get("BRONCHO_UPDATE_GOLDEN") == "1"


@pytest.fixture(scope="module")
def built(golden_store):
    client, _, ids = golden_store
    index = collect.collect_runs(client, EXPERIMENT, SWEEP)
    ctx = tables.ReportContext(index, profiler=PROFILES.get)
    out = {}
    for build in tables.TABLES.values():
        for ev in ("accumulated", "pair"):
            t = build(ctx, ev)
            out[t.key] = t
    return out, {v: f"<{k}>" for k, v in ids.items()}


def normalise(text: str, names: dict[str, str]) -> str:
    return re.sub(r"\b[0-9a-f]{32}\b", lambda m: names.get(m.group(0), "<unknown-run>"), text)


KEYS = [f"table{n}-{kind}-{ev}" for n, kind in ((2, "personalized"), (3, "personalized"), (4, "cross-subject"),
                                                  (5, "cross-subject"), (6, "sota"), (7, "ablation"))
        for ev in ("accumulated", "pair")
        if not ((n in (2, 4) and ev == "pair") or (n in (3, 5) and ev == "accumulated"))]


@pytest.mark.parametrize("key", KEYS)
@pytest.mark.parametrize("suffix", ["md", "tex"])
def test_table_matches_golden_file(built, key, suffix):
    tabs, names = built
    render = to_markdown if suffix == "md" else to_latex
    text = normalise(render(tabs[key]), names)
    path = GOLDEN / f"{key}.{suffix}"
    if UPDATE:
        path.parent.mkdir(exist_ok=True)
        path.write_text(text, encoding="utf-8")
    assert path.is_file(), f"{path} missing: run with BRONCHO_UPDATE_GOLDEN=1 and review it"
    assert text == path.read_text(encoding="utf-8")


def _row(text: str, group: str, loss: str) -> str:
    """The LaTeX row of ``loss`` in ``group`` (group name only on the group's first row)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"{group} & "))
    return next(line for line in lines[start:] if f"& {loss} &" in line)


def test_latex_highlighting_of_table2_follows_the_planted_values(built):
    tabs, _ = built
    tex = to_latex(tabs["table2-personalized-accumulated"])
    cells = lambda g, lo: _row(tex, g, lo).rstrip(" \\").split(" & ")[2:]  # noqa: E731
    pos, rot, de, ce = zip(*[cells("+ConvRNN", lo) for lo in ("MSE+MSE", "MSE+DE", "MSE+CE")])
    # Position L2: ConvLSTM MSE+CE 2.00 is the column best (red) and its group best (bold); MSE+DE 2.20 second (blue).
    assert pos[2] == r"\textcolor{red}{\textbf{2.00 \ensuremath{\pm} 1.00}}"
    assert pos[1] == r"\textcolor{blue}{2.20 \ensuremath{\pm} 1.10}"
    assert pos[0] == r"2.80 \ensuremath{\pm} 1.40"
    # Rotation L2: 12.0 appears twice (LSTM MSE+CE and ConvLSTM MSE+MSE): both red; 12.5 is second.
    assert rot[0] == r"\textcolor{red}{\textbf{12.0 \ensuremath{\pm} 6.0}}"
    assert rot[2] == r"\textcolor{blue}{12.5 \ensuremath{\pm} 6.2}"
    assert cells("+LSTM", "MSE+CE")[1] == r"\textcolor{red}{\textbf{12.0 \ensuremath{\pm} 6.0}}"
    # A group best that is not a column best is only bold.
    assert cells("Baseline", "MSE+DE")[0] == r"\textbf{4.00 \ensuremath{\pm} 2.00}"
    assert de[1].startswith(r"\textcolor{red}") and ce[2].startswith(r"\textcolor{red}")
    # The missing cell (conv3d MSE+CE only FAILED) is an em dash in every column.
    assert _row(tex, "+3D", "MSE+CE").endswith("& --- & --- & --- & --- \\\\")


def test_markdown_marks_and_warnings(built):
    tabs, names = built
    md = normalise(to_markdown(tabs["table2-personalized-accumulated"]), names)
    assert "| +ConvRNN | MSE+MSE | 2.80 ± 1.40 | **_12.0 ± 6.0_**† |" in md
    assert "|  | MSE+DE | _2.20 ± 1.10_‡ |" in md
    assert "|  | MSE+CE | — | — | — | — |" in md
    assert ("> **Warning:** duplicate: lstm/ce/personalized/s0/world has 2 FINISHED runs; using the latest "
            "<personalized/lstm/ce>, ignoring <personalized/lstm/ce-old>") in md
    assert "no FINISHED run (<personalized/conv3d/ce-failed> FAILED (FloatingPointError: loss is nan))" in md


def test_duplicate_uses_the_latest_finished_run(built):
    tabs, names = built
    row = next(r for r in tabs["table2-personalized-accumulated"].rows if (r.group, r.label) == ("+LSTM", "MSE+CE"))
    assert [names[i] for i in row.runs] == ["<personalized/lstm/ce>"]
    assert row.values[0].mean == pytest.approx(2.5)  # the older duplicate has 9.9


def test_trials_and_other_sweeps_are_ignored(built):
    tabs, names = built
    every = {i for t in tabs.values() for r in t.rows for i in r.runs}
    assert all(i in names for i in every)  # only runs of the golden sweep's cells
