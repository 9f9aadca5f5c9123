"""Issue 56 item 4: Table 6's note puts our direction beside the paper's and names every remaining difference."""

from __future__ import annotations

from bronchocli.reporting.collect import RunRecord
from bronchocli.reporting.context import metrics_of
from bronchocli.reporting.table_model import Column, Estimate, Row, Table
from bronchocli.reporting.tables import _beside_paper
from bronchocli.runs.records import TAG_INIT


def table(pos: tuple[float, float], ce: tuple[float, float], best: dict[str, int]) -> Table:
    """Two model rows (BronchoTrack, OffsetNet) with a Params column, then a reference row; ``best``: metric ->
    the row index the table bolded."""
    metrics = metrics_of("paper")
    values = {m: (Estimate(1.0), Estimate(2.0)) for m in metrics}
    values["pos_l2"], values["ce"] = (Estimate(pos[0]), Estimate(pos[1])), (Estimate(ce[0]), Estimate(ce[1]))
    rows = [Row("", name, [Estimate(5.0)] + [values[m][i] for m in metrics], model=name)
            for i, name in enumerate(("BronchoTrack", "OffsetNet"))]
    rows.append(Row("", "Training mean", [None] + [Estimate(9.0)] * len(metrics), kind="reference"))
    marks = [[set() for _ in range(1 + len(metrics))] for _ in rows]
    for m, i in best.items():
        marks[i][1 + metrics.index(m)].add("best")
    return Table("table6-sota-accumulated", "Table 6", ("Model",), [Column("Params")] + [Column(m) for m in metrics],
                 rows, marks=marks)


def run(init: str) -> RunRecord:
    return RunRecord("r", "FINISHED", 0, {TAG_INIT: init}, {})


def test_offsetnet_lower_in_position_is_said_so_with_its_significance_and_the_differences():
    note = _beside_paper(table((52.0, 26.5), (0.05, 0.06), {"pos_l2": 1}), [run("random")] * 4, 96)
    assert note.startswith("Here: position L2 BronchoTrack 52 vs OffsetNet 26.5 vox; CE BronchoTrack 0.05 vs "
                           "OffsetNet 0.06 — OffsetNet lower in position; BronchoTrack lower in CE (position "
                           "significantly, CE not significantly")
    assert "96² frames (the paper: 256²)" in note
    assert "patients not known (no per-trajectory errors) (the paper: 5 CT patients)" in note  # no samples here
    assert "backbones from random weights (the paper: ImageNet)" in note


def test_one_winner_in_both_and_an_imagenet_start():
    note = _beside_paper(table((4.9, 5.7), (0.8, 0.99), {}), [run("imagenet:lite0.pth")] * 2, 256)
    assert "— BronchoTrack lower in both (position not significantly, CE not significantly" in note
    assert "backbones from ImageNet weights (the paper: ImageNet)" in note


def test_unknown_size_and_mixed_or_unrecorded_starts_are_said_so():
    note = _beside_paper(table((2.0, 1.0), (0.1, 0.2), {}), [run("random"), run("imagenet:x.pth")], None)
    assert "frames of unrecorded size (the paper: 256²)" in note and "backbones from mixed weights" in note
    assert "backbones from unrecorded weights" in _beside_paper(table((2.0, 1.0), (0.1, 0.2), {}), [run("")], 96)


def test_without_both_model_rows_there_is_no_note():
    t = table((1.0, 2.0), (0.1, 0.2), {})
    t.rows = t.rows[:1] + t.rows[2:]
    assert _beside_paper(t, [run("random")], 96) == ""
