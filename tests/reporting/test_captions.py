"""Captions a journal would print (issue 48): at most three sentences, n in the evaluation's unit, footnotes for the
marks a table uses only, no internal key names; Table 6's caption within 600 characters in Markdown and LaTeX."""

from __future__ import annotations

import re

import pytest
from report_fakes import golden_tables

from bronchocli.reporting.captions import footnotes, methods_pointer
from bronchocli.reporting.latex import to_latex
from bronchocli.reporting.markdown import to_markdown

# What a reader must never meet in a caption: tags, params and metric keys (snake_case or dotted), file paths.
INTERNAL = [
    re.compile(r"\b[a-z][a-z0-9]*(?:_[a-z0-9]+)+\b"),  # cell_key, n_params, train_trajectories, pos_l2
    re.compile(r"\b[a-z][a-z0-9_]+\.[a-z_][a-z0-9_.]*\b"),  # speed.precision, val_best.pos_l2, pred.std_ratio.pos
    re.compile(r"[\w./-]*\.(?:md|py|csv|json|yaml|tex)\b"),  # docs/reports.md, trajectory_errors.csv
]


def internal_names(text: str) -> list[str]:
    return [m.group(0) for rx in INTERNAL for m in rx.finditer(text)]


@pytest.mark.parametrize("text, found", [
    ("the runs of this config's cells (cell_key)", "cell_key"),
    ("every row trained at fp32 (speed.precision).", "speed.precision"),
    ("trainable parameters (n_params), millions", "n_params"),
    ("calibrated by simulation, docs/reports.md]", "docs/reports.md"),
    ("top 1 by val_best.pos_l2", "val_best.pos_l2"),
])
def test_the_checker_finds_internal_names(text, found):
    assert found in internal_names(text)


@pytest.fixture(scope="module")
def built(golden_store):
    return golden_tables(golden_store)[0]


def _sentences(caption: str) -> int:
    return len(re.findall(r"\.(?:\s|$)", caption))


def test_every_caption_is_at_most_three_sentences_and_names_no_internal_key(built):
    assert len(built) == 11
    for key, t in built.items():
        assert 0 < _sentences(t.caption) <= 3, (key, t.caption)
        printed = " ".join([t.caption] + [text for _, text in footnotes(t)])
        assert internal_names(printed) == [], (key, internal_names(printed))


@pytest.mark.parametrize("evaluation", ["accumulated", "pair"])
def test_table6_caption_fits_600_characters_in_markdown_and_latex(built, evaluation):
    t = built[f"table6-sota-{evaluation}"]
    md = to_markdown(t)
    assert methods_pointer(t.caption, "md") in md and len(t.caption) <= 600
    tex = to_latex(t)
    caption = re.search(r"\\caption\{(.*)\}\n\\label", tex).group(1)
    assert len(caption) <= 600
    assert "+ConvRNN MSE+DE" in t.caption and "role of the paper's BronchoTrack" in t.caption and "OffsetNet" in t.caption
    assert "for new seeds and new test trajectories of these 3 patients (p00, p01, p02), not a new patient" in \
        t.caption


def test_n_is_stated_in_the_unit_of_the_evaluation(built):
    acc, pair = built["table2-personalized-accumulated"].caption, built["table3-personalized-pair"].caption
    assert "× 24 test trajectories (one final pose each)" in acc and "pairs)" not in acc
    assert re.search(r"× 24 test trajectories \(\d+ pairs\)", pair)
    assert "scored frames)" in built["table9-tracking"].caption
    assert "of 3 held-out patients" in built["table4-cross-subject-accumulated"].caption


def test_footnotes_only_for_the_marks_the_table_uses(built):
    sota = dict(footnotes(built["table6-sota-pair"]))
    assert {"bold", "†"} <= sota.keys() and not {"bold≈", "‡", "—"} & sota.keys()  # no tie, ‡ or missing cell there
    tracking = dict(footnotes(built["table9-tracking"]))
    assert {"bold", "bold≈", "†", "‡", "—"} <= tracking.keys()
    assert "no single best at 3 seeds in RPE rot." in tracking["bold≈"]
    md = to_markdown(built["table6-sota-pair"])
    assert "≈:" not in md and "‡" not in md
    tex = to_latex(built["table6-sota-pair"])
    assert r"\begin{threeparttable}" in tex and r"\item[] \textbf{Bold}: significantly better" in tex
    assert tex.index(r"\end{tablenotes}") < tex.index("% --- table ends") < tex.index("Source: Sweep 'golden'")
