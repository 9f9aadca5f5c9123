"""The frame-convention table, the learning curve and the skill figures, from in-memory runs."""

from __future__ import annotations

import pytest
from PIL import Image
from report_fakes import MemRuns, frames_runs

from bronchocli.reporting.context import NoData
from bronchocli.reporting.markdown import to_markdown
from bronchocli.reporting.report import build_tables, make_report
from bronchocli.reporting.skill_figures import curve_points
from bronchocli.reporting.table_model import Estimate
from bronchocli.reporting.tables import frames


def test_frames_table_compares_skill_in_each_frames_own_terms():
    t = frames(frames_runs().context(), "pair")
    assert t.key == "table8-frames-pair"
    assert [r.label for r in t.rows] == ["+LSTM MSE+CE", "BronchoTrack"]  # the models by their one name
    lstm, convlstm = t.rows
    world, camera, p = lstm.values[:3]
    assert isinstance(world, Estimate) and world.mean == pytest.approx(1 - 3.48 / 5.8, abs=0.03)
    assert camera.mean == pytest.approx(1 - 0.58 / 2.9, abs=0.03)
    assert p.endswith("(significant)")
    assert convlstm.values[0].mean == pytest.approx(convlstm.values[1].mean, abs=0.03)
    assert not convlstm.values[2].endswith("(significant)")
    assert "Holm-corrected over the rows" in t.notes[0] and "own" not in t.warnings


def test_frames_table_needs_both_frames_and_is_skipped_with_one_line():
    m = MemRuns(seed=12)
    m.add("lstm", "ce")
    with pytest.raises(NoData, match="not both world and camera"):
        frames(m.context(), "pair")
    notes: list[str] = []
    assert build_tables(m.context(), ["frames"], ["accumulated", "pair"], notes) == []
    assert notes == ["frames table skipped: the runs have pose frame(s) world, not both world and camera"]


def test_main_tables_use_one_frame_when_runs_span_both():
    ctx = frames_runs().context()
    t = build_tables(ctx, ["personalized"], ["pair"])[0]
    assert "pose frame 'world'" in t.source[0]
    assert any("the main tables use world" in n for n in ctx.index.notes)
    md = to_markdown(t)
    assert md.count("| +LSTM |") == 1


def _curve_runs() -> MemRuns:
    m = MemRuns(seed=13)
    for size, scale, pairs in (("2", 2.0, 100.0), ("4", 1.4, 200.0), ("", 1.0, 400.0)):
        for arch in ("lstm", "convlstm"):
            m.add(arch, "ce", (2.5, 10.0, 0.1, 0.01), size=size, scale=scale, train_pairs=pairs)
    return m


def test_learning_curve_points_follow_the_training_set_size():
    ctx = _curve_runs().context(default_train_trajectories=8)
    data = curve_points(ctx)
    assert list(data["points"]) == ["2", "4", ""]
    assert [p["x"] for p in data["points"].values()] == [100.0, 200.0, 400.0]
    assert [p["label"] for p in data["points"].values()] == ["2", "4", "8"]
    errors = [next(r for r in p["rows"] if r.name == "+LSTM MSE+CE").values[0].mean for p in data["points"].values()]
    assert errors[0] > errors[1] > errors[2]  # more data, less error (planted)
    skills = [p["skill"]["+LSTM MSE+CE"]["pos_l2"].value for p in data["points"].values()]
    assert skills[0] < skills[1] < skills[2]


def test_make_report_writes_the_learning_curve_and_a_skill_figure_per_table(tmp_path):
    ctx = _curve_runs().context(default_train_trajectories=8)
    warnings: list[str] = []
    result = make_report(ctx, ["personalized", "frames"], ["pair"], ["md"], tmp_path, loader=lambda run: None,
                         warnings=warnings)
    names = sorted(p.name for p in result.files)
    assert {"fig-learning-curve.png", "fig-learning-curve.pdf", "fig-skill-table3-personalized-pair.png",
            "fig-skill-table3-personalized-pair.pdf", "table3-personalized-pair.md"} <= set(names)
    with Image.open(tmp_path / "fig-learning-curve.png") as im:
        assert im.size[0] > 600
    assert sum("frames table skipped" in w for w in result.warnings) == 1
    assert any("train_trajectories: the runs span 2, 4, default" in w for w in result.warnings)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import matplotlib.pyplot as plt

    plt.close("all")


def test_frames_table_at_two_seeds_reads_skill_for_the_trained_models():
    m = MemRuns(seed=13)
    for seed in (0, 1):
        m.add("lstm", "ce", (3.48, 13.8, 0.20, 0.04), seed=seed, frame="world")
        m.add("lstm", "ce", (0.58, 2.3, 0.03, 0.007), seed=seed, frame="camera")
    t = frames(m.context(), "pair")
    world, camera, p = t.rows[0].values[:3]
    assert isinstance(world, Estimate) and world.has_interval and camera.has_interval and p != "—"
    assert "2 seeds, fixed: not new seeds" in t.caption
    assert not any("Means only" in n for n in t.notes)
