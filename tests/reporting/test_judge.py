"""Table rows with intervals, references and marks, on in-memory runs with planted per-trajectory errors."""

from __future__ import annotations

import numpy as np
import pytest
from report_fakes import REFS, MemRuns

from bronchocli.reporting import judge, stats
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
    a, b = _row(t, "+LSTM", "MSE+CE"), _row(t, "+ConvRNN", "MSE+CE")
    assert t.marks[a][0] == {"tie"} and t.marks[b][0] == {"tie"}
    assert not any("best" in mk for row in t.marks for mk in row)


def test_a_clearly_better_row_is_the_single_best():
    m = MemRuns(seed=2)
    for seed in (0, 1, 2):
        m.add("lstm", "ce", (2.0, 10.0, 0.10, 0.010), seed=seed)
        m.add("convlstm", "ce", (2.4, 12.0, 0.12, 0.012), seed=seed)
    t = personalized(m.context(), "accumulated")
    a, b = _row(t, "+LSTM", "MSE+CE"), _row(t, "+ConvRNN", "MSE+CE")
    for j in METRIC_COLS:
        assert t.marks[a][j] == {"best"} and t.marks[b][j] == set()


def test_holm_decides_between_best_and_tie_on_three_rows(monkeypatch):
    # Raw p of the best against the two others: 0.03 and 0.04, both < 0.05; Holm: 2*0.03 = 0.06,
    # max(0.06, 0.04) = 0.06 -> neither is significant after correction: the three rows tie.
    samples = [stats.Sample((("p", "l", "t"),), np.ones(1), np.array([[v]])) for v in (1.0, 2.0, 3.0)]
    p_of = {2.0: 0.03, 3.0: 0.04}
    monkeypatch.setattr(stats, "paired_p", lambda a, b, *_: p_of[b.mean])
    marks, adjusted = judge.judge_column(samples, judge.Settings())
    assert adjusted == {1: pytest.approx(0.06), 2: pytest.approx(0.06)}
    assert marks == [{"tie"}, {"tie"}, {"tie"}]
    p_of.update({2.0: 0.02, 3.0: 0.024})  # Holm: 0.04 and 0.04 -> both significant: a single best
    marks, adjusted = judge.judge_column(samples, judge.Settings())
    assert adjusted == {1: pytest.approx(0.04), 2: pytest.approx(0.04)}
    assert marks == [{"best"}, set(), set()]


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
    assert "ignores its input" in t.caption


def test_cell_mean_is_the_mean_over_seeds_of_the_logged_run_metric():
    m = MemRuns(seed=6)
    runs = [m.add("lstm", "ce", (2.0, 10.0, 0.1, 0.01), seed=s, noise=0.2) for s in (0, 1, 2)]
    for ev, name in (("pair", "pair.pos_l2.mean"), ("accumulated", "acc.pos_l2.mean")):
        t = personalized(m.context(), ev)
        assert t.rows[0].values[0].mean == pytest.approx(np.mean([r.metrics[name] for r in runs]))
    assert "n per cell = 3 seeds × 24 test trajectories" in t.caption


def test_cross_subject_replicate_is_the_union_of_its_folds():
    m = MemRuns(seed=7)
    runs = [m.add("lstm", "ce", (2.0 + f, 10.0, 0.1, 0.01), population="cross-subject", fold=p, seed=0)
            for f, p in enumerate(("p00", "p01"))]
    t = cross_subject(m.context(), "pair")
    w = [r.metrics["test.n_pairs"] for r in runs]
    pooled = sum(wi * r.metrics["pair.pos_l2.mean"] for wi, r in zip(w, runs)) / sum(w)
    assert t.rows[0].values[0].mean == pytest.approx(pooled)
    assert "of 2 held-out patients" in t.caption and "held-out: p00, p01" in t.caption


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
    lstm, conv = _row(t, "+LSTM", "MSE+CE"), _row(t, "+ConvRNN", "MSE+CE")
    assert t.marks[lstm][0] == {"best"} and t.rows[lstm].values[0].mean > t.rows[conv].values[0].mean  # CTF
    assert t.marks[lstm][2] == {"best"} and t.rows[lstm].values[2].mean < t.rows[conv].values[2].mean  # ATE
    assert [r.label for r in t.rows if r.kind == "reference"] == ["Zero motion", "Training mean"]
    assert all(isinstance(v, Estimate) and v.has_interval for r in t.rows for v in r.values)
    assert tables.evaluations("both") == ["accumulated", "pair"]
