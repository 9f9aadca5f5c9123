"""Table rows with intervals, references and marks, on in-memory runs with planted per-trajectory errors."""

from __future__ import annotations

import numpy as np
import pytest
from report_fakes import REFS, MemRuns

from bronchocli.reporting import judge, stats
from bronchocli.reporting.captions import footnotes
from bronchocli.reporting.table_model import Estimate
from bronchocli.reporting.tables import ablation, cross_subject, personalized, sota

METRIC_COLS = range(4)


def _row(table, group, label):
    return next(i for i, r in enumerate(table.rows) if (r.group, r.label) == (group, label))


def test_rows_closer_than_their_noise_are_a_tie():
    m = MemRuns(seed=1)
    for seed in (0, 1, 2):
        m.add("lstm", "ce", (2.000, 10.0, 0.10, 0.010), seed=seed, noise=0.10)
        m.add("convlstm", "ce", (2.004, 10.1, 0.10, 0.010), seed=seed, noise=0.10)
    t = personalized(m.context(), "accumulated")
    a, b = _row(t, "+LSTM", "MSE+CE"), _row(t, "+ConvRNN", "MSE+CE (BronchoTrack)")
    assert t.marks[a][0] == {"tie"} and t.marks[b][0] == {"tie"}
    assert not any("best" in mk for row in t.marks for mk in row)


def test_a_clearly_better_row_is_the_single_best():
    m = MemRuns(seed=2)
    for seed in (0, 1, 2):
        m.add("lstm", "ce", (2.0, 10.0, 0.10, 0.010), seed=seed)
        m.add("convlstm", "ce", (2.4, 12.0, 0.12, 0.012), seed=seed)
    t = personalized(m.context(), "accumulated")
    a, b = _row(t, "+LSTM", "MSE+CE"), _row(t, "+ConvRNN", "MSE+CE (BronchoTrack)")
    for j in METRIC_COLS:
        assert t.marks[a][j] == {"best"} and t.marks[b][j] == set()


def test_holm_over_every_pair_decides_between_best_and_tie_on_three_rows(monkeypatch):
    # The best is chosen by the data, so the family is every pair of rows (3 pairs here), not only best vs others.
    samples = [stats.Sample((("p", "l", "t"),), np.ones(1), np.array([[v]])) for v in (1.0, 2.0, 3.0)]
    p_of = {(1.0, 2.0): 0.01, (1.0, 3.0): 0.02, (2.0, 3.0): 0.5}
    monkeypatch.setattr(stats, "paired_p", lambda a, b, *_: p_of[tuple(sorted((a.mean, b.mean)))])
    marks, adjusted = judge.judge_column(samples, judge.Settings())
    # Holm over 3: 3 * 0.01 = 0.03, max(0.03, 2 * 0.02) = 0.04, 0.5 -> both significant: a single best
    assert adjusted == {1: pytest.approx(0.03), 2: pytest.approx(0.04)}
    assert marks == [{"best"}, set(), set()]
    # raw 0.02 and 0.024: Holm over the two best-vs-other comparisons gave 0.04 / 0.04 (a single best); over the
    # three pairs 0.06 / 0.06: the selection of the best is paid for, the three rows tie
    p_of.update({(1.0, 2.0): 0.02, (1.0, 3.0): 0.024})
    marks, adjusted = judge.judge_column(samples, judge.Settings())
    assert adjusted == {1: pytest.approx(0.06), 2: pytest.approx(0.06)}
    assert marks == [{"tie"}, {"tie"}, {"tie"}]


def test_tied_with_best_is_batched_and_picks_the_highest_where_higher_is_better():
    means = np.array([[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]])
    p = np.array([[[1, 0.001, 0.001], [0.001, 1, 0.9], [0.001, 0.9, 1]]] * 2)
    best, vs_best, tied = stats.tied_with_best(means, p)
    assert best.tolist() == [0, 2] and tied.tolist() == [[True, False, False], [False, True, True]]
    assert vs_best[0].tolist() == pytest.approx([1.0, 0.003, 0.003])
    best, _, tied = stats.tied_with_best(means, p, higher=True)
    assert best.tolist() == [2, 0] and tied.tolist() == [[False, True, True], [True, False, False]]


def test_reference_rows_are_present_for_every_metric_and_both_evaluations():
    m = MemRuns(seed=3)
    m.add("convlstm", "ce")
    m.add("offsetnet", "mse")
    for t in (build(m.context(), ev) for build in (personalized, sota, ablation) for ev in ("accumulated", "pair")):
        refs = [r for r in t.rows if r.kind == "reference"]
        assert [r.label for r in refs] == ["Zero motion", "Training mean"]
        n_extra = sum(not c.highlight for c in t.columns)
        for r in refs:
            assert all(isinstance(v, Estimate) and v.has_interval for v in r.values[n_extra:])


def test_reference_values_match_the_planted_trajectories():
    m = MemRuns(seed=4)
    m.add("lstm", "ce", seed=0)
    m.add("lstm", "ce", seed=1)
    t = personalized(m.context(), "accumulated")
    zero = next(r for r in t.rows if r.label == "Zero motion")
    # acc scope: unweighted mean over trajectories of zero_motion.acc.pos_l2, the same in both runs
    expected = np.mean([m.errors[r.run_id].columns["zero_motion.acc.pos_l2"] for r in m.records], axis=0).mean()
    assert zero.values[0].mean == pytest.approx(expected)
    assert zero.values[0].mean == pytest.approx(REFS["zero_motion"][0], rel=1e-9)


def test_a_row_no_better_than_the_reference_and_one_that_ignores_its_input_are_marked():
    m = MemRuns(seed=5)
    m.add("lstm", "ce", (2.0, 10.0, 0.10, 0.010))
    m.add("lstm", "mse", (6.0, 23.5, 0.35, 0.073), ratio=0.01)  # at the references' level, constant output
    t = personalized(m.context(), "pair")
    good, bad = _row(t, "+LSTM", "MSE+CE"), _row(t, "+LSTM", "MSE+MSE")
    assert all("noskill" in t.marks[bad][j] for j in METRIC_COLS)
    assert not any("noskill" in t.marks[good][j] for j in METRIC_COLS)
    assert t.rows[bad].flags == {"ignores"} and t.rows[good].flags == set()
    assert ("‡", "the model ignores its input: its predictions vary less than 5% of the ground truth's.") in \
        footnotes(t)


def test_cell_mean_is_the_mean_over_seeds_of_the_logged_run_metric():
    m = MemRuns(seed=6)
    runs = [m.add("lstm", "ce", (2.0, 10.0, 0.1, 0.01), seed=s, noise=0.2) for s in (0, 1, 2)]
    for ev, name in (("pair", "pair.pos_l2.mean"), ("accumulated", "acc.pos_l2.mean")):
        t = personalized(m.context(), ev)
        assert t.rows[0].values[0].mean == pytest.approx(np.mean([r.metrics[name] for r in runs]))
    assert "n = 3 seeds × 24 test trajectories" in t.caption


def test_cross_subject_replicate_is_the_union_of_its_folds():
    m = MemRuns(seed=7)
    runs = [m.add("lstm", "ce", (2.0 + f, 10.0, 0.1, 0.01), population="cross-subject", fold=p, seed=0)
            for f, p in enumerate(("p00", "p01"))]
    t = cross_subject(m.context(), "pair")
    w = [r.metrics["test.n_pairs"] for r in runs]
    pooled = sum(wi * r.metrics["pair.pos_l2.mean"] for wi, r in zip(w, runs)) / sum(w)
    assert t.rows[0].values[0].mean == pytest.approx(pooled)
    assert "of 2 held-out patients" in t.caption and any("every held-out patient (p00, p01)" in n for n in t.notes)


def test_a_seed_missing_a_fold_is_left_out_and_said_so():
    m = MemRuns(seed=8)
    for p in ("p00", "p01"):
        m.add("lstm", "ce", population="cross-subject", fold=p, seed=0)
    m.add("lstm", "ce", population="cross-subject", fold="p00", seed=1)  # seed 1 lacks fold p01
    m.add("lstm", "ce", population="cross-subject", fold="p01", seed=1, status="FAILED")
    t = cross_subject(m.context(), "accumulated")
    assert t.rows[0].info["replicates"] == 1 and len(t.rows[0].runs) == 2
    lacks = [w for w in t.warnings if "lacks" in w]
    assert len(lacks) == 1 and "lstm/ce/cross-subject/p01/s1/world (FAILED" in lacks[0]


def test_runs_without_trajectory_errors_fall_back_to_logged_means():
    m = MemRuns(seed=9)
    old = m.add("lstm", "ce", (2.0, 10.0, 0.1, 0.01), with_errors=False)
    m.add("convlstm", "ce", (3.0, 10.0, 0.1, 0.01))
    t = personalized(m.context(), "accumulated")
    row = t.rows[_row(t, "+LSTM", "MSE+CE")]
    assert row.values[0] == Estimate(old.metrics["acc.pos_l2.mean"])  # no interval
    assert all(not mk for mk in t.marks[_row(t, "+LSTM", "MSE+CE")][:4] if mk != {"noskill"})
    assert any("no trajectory_errors.csv for +LSTM MSE+CE" in w for w in t.warnings)


def test_skill_is_one_minus_error_over_the_better_reference():
    m = MemRuns(seed=10)
    m.add("lstm", "ce", (2.0, 10.0, 0.1, 0.01))
    t = personalized(m.context(), "accumulated")
    refs = {r.label: r.values[0].mean for r in t.rows if r.kind == "reference"}
    d = t.skill["+LSTM MSE+CE"]["pos_l2"]
    assert d.value == pytest.approx(1 - t.rows[0].values[0].mean / min(refs.values()))
    assert d.lo < d.value < d.hi


def test_a_higher_is_better_column_marks_the_highest_mean_and_no_skill_from_above():
    def sample(values):
        return stats.Sample(tuple(("p", "l", f"t{i}") for i in range(len(values))), np.ones(len(values)),
                            np.array([values]))
    rng = np.random.default_rng(12)
    hard = rng.uniform(40, 60, 20)
    high, low = sample(hard + 10 + rng.normal(0, 0.5, 20)), sample(hard + rng.normal(0, 0.5, 20))
    marks, _ = judge.judge_column([low, high], judge.Settings(), higher=True)
    assert marks == [set(), {"best"}]
    marks, _ = judge.judge_column([low, high], judge.Settings())
    assert marks == [{"best"}, set()]


def test_the_tracking_table_is_built_once_with_both_references():
    from bronchocli.reporting import report, tables

    m = MemRuns(seed=11)
    for seed in (0, 1, 2):
        m.add("lstm", "ce", (2.0, 10.0, 0.10, 0.010), seed=seed)
        m.add("convlstm", "ce", (4.0, 14.0, 0.12, 0.012), seed=seed)
    built = report.build_tables(m.context(), ["tracking"], ["accumulated", "pair"])
    assert [t.key for t in built] == ["table9-tracking"]
    t = built[0]
    lstm, conv = _row(t, "+LSTM", "MSE+CE"), _row(t, "+ConvRNN", "MSE+CE (BronchoTrack)")
    assert t.marks[lstm][0] == {"best"} and t.rows[lstm].values[0].mean > t.rows[conv].values[0].mean  # CTF
    assert t.marks[lstm][2] == {"best"} and t.rows[lstm].values[2].mean < t.rows[conv].values[2].mean  # ATE
    assert [r.label for r in t.rows if r.kind == "reference"] == ["Zero motion", "Training mean"]
    assert all(isinstance(v, Estimate) and v.has_interval for r in t.rows for v in r.values)
    assert tables.evaluations("both") == ["accumulated", "pair"]


def _shared_difficulty_runs(factor: float, seed: int = 13):
    """3 seeds of OffsetNet and ConvLSTM/CE at ``factor`` x the better reference on every metric, on trajectories
    whose difficulty varies e-fold and is shared with the references (what the pairing cancels)."""
    from report_fakes import difficulty

    m = MemRuns(seed=seed)
    m.hard = difficulty(m.keys, seed=seed, spread=0.8)
    near = tuple(factor * min(z, t) for z, t in zip(REFS["zero_motion"], REFS["train_mean"]))
    for s in (0, 1, 2):
        m.add("offsetnet", "mse", near, seed=s, noise=0.02)
        m.add("convlstm", "ce", near, seed=s, noise=0.02)
    return m


def _bar_colours(fig) -> list[list[bool]]:
    """Per axis (metric), whether each bar is blue (the figure's 'beats the reference')."""
    from matplotlib.colors import to_rgba

    blue = to_rgba("tab:blue")
    return [[p.get_facecolor() == blue for p in ax.patches] for ax in fig.axes]


def test_dagger_and_skill_colour_are_one_paired_verdict_where_the_unpaired_rule_disagreed():
    # The row is 10 % better than the reference on every trajectory, but trajectories differ e-fold in difficulty:
    # its own interval (over seeds and trajectories) reaches above the reference's mean, so the earlier rule (row
    # interval vs reference mean) marked † while the paired skill interval lay above 0 (blue) - the issue's
    # OffsetNet Rotation L2 0.463 [0.145, 0.662] with †. Now both come from the paired comparison.
    from bronchocli.reporting.skill_figures import skill_figure

    m = _shared_difficulty_runs(0.9)
    t = sota(m.context(), "accumulated")
    ref_mean = min(r.values[1].mean for r in t.rows if r.kind == "reference")
    i = next(i for i, r in enumerate(t.rows) if r.name.startswith("OffsetNet"))
    cell = t.rows[i].values[1]  # Position L2 (after Params)
    assert cell.hi >= ref_mean  # the old rule's †
    d = t.skill[t.rows[i].name]["pos_l2"]
    assert d.lo > 0 and judge.beats_reference(d)
    assert "noskill" not in t.marks[i][1]
    fig = skill_figure(t)
    names = [r.name for r in t.rows if r.kind == "model" and r.name in t.skill]
    # every error column of the table has its panel (DE, CE too), and nothing is said about 2 seeds at 3
    assert [ax.get_ylabel() for ax in fig.axes] == ["skill, Position L2", "skill, Rotation L2", "skill, DE",
                                                     "skill, CE"]
    assert "seeds" not in fig._suptitle.get_text() and "no bar" not in fig._suptitle.get_text()
    for ax_blue, metric in zip(_bar_colours(fig), ("pos_l2", "rot_l2", "de", "ce")):
        for name, blue in zip(names, ax_blue):
            row = next(k for k, r in enumerate(t.rows) if r.name == name)
            column = 1 + ["pos_l2", "rot_l2", "de", "ce"].index(metric)
            assert blue == ("noskill" not in t.marks[row][column]) == judge.beats_reference(t.skill[name][metric])


def test_a_lower_bound_that_touches_0_is_written_out():
    from bronchocli.reporting.skill_figures import skill_figure
    from bronchocli.reporting.table_model import Column, Row, Table

    rows = [Row("", "A", [1.0], ["r1"]), Row("", "B", [1.0], ["r2"])]
    t = Table("t", "T", ("Model",), [Column("Position L2")], rows)
    t.skill = {"A": {"pos_l2": stats.Derived(0.30, -0.003, 0.6, 0.06, 4.0)},
               "B": {"pos_l2": stats.Derived(0.50, 0.25, 0.75, 0.001, 4.0)}}
    fig = skill_figure(t)
    texts = [x.get_text() for x in fig.axes[0].texts]
    assert texts == ["-0.003"]  # A's bound, not B's (far from 0)
    assert "a lower bound at 0 is written out" in " ".join(fig._suptitle.get_text().split())


def test_a_row_at_the_references_level_is_dagger_and_grey_by_the_same_test():
    from bronchocli.reporting.skill_figures import skill_figure

    m = _shared_difficulty_runs(1.0, seed=14)
    t = sota(m.context(), "accumulated")
    for i, r in enumerate(t.rows):
        if r.kind == "model":
            assert all("noskill" in t.marks[i][j] for j in range(1, 5))
            assert not any(judge.beats_reference(d) for d in t.skill[r.name].values())
    assert not any(any(col) for col in _bar_colours(skill_figure(t)))
