"""Every table states its estimand (these patients / a new patient), refuses what too few replicates cannot
support, and keeps bounded figures inside their bounds (issue 28)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from report_fakes import MemRuns

from bronchocli.reporting import stats
from bronchocli.reporting.aggregate import reference_sample, replicates
from bronchocli.reporting.table_model import Estimate
from bronchocli.reporting.tables import cross_subject, personalized, tracking

PATIENT_DIFFICULTY = {"p00": 0.6, "p01": 1.0, "p02": 1.7}  # a hard patient is hard for every trajectory of it


def _clustered(patients=("p00", "p01", "p02"), seed: int = 3) -> MemRuns:
    m = MemRuns(seed=seed, keys=[k for k in MemRuns().keys if k[0] in patients])
    for key, h in m.hard.items():
        h["acc"] *= PATIENT_DIFFICULTY[key[0]]
        h["pair"] *= PATIENT_DIFFICULTY[key[0]]
    return m


def _cross_sweep(patients=("p00", "p01", "p02"), seeds=(0, 1, 2)) -> MemRuns:
    """A tiny cross-subject sweep: 2 networks, one run per (seed, held-out patient)."""
    m = _clustered(patients)
    for seed in seeds:
        for p in patients:
            m.add("lstm", "ce", (2.0, 10.0, 0.10, 0.010), population="cross-subject", fold=p, seed=seed)
            m.add("convlstm", "ce", (2.3, 11.0, 0.11, 0.011), population="cross-subject", fold=p, seed=seed)
    return m


def test_cross_subject_caption_states_a_new_patient_and_how_many_patients():
    t = cross_subject(_cross_sweep().context(), "accumulated")
    assert "for a new patient (new seeds, patients and trajectories)" in t.caption
    assert "resting on 3 patients (p00, p01, p02), hence wide" in t.caption
    row = t.rows[0]
    sample = row.info["samples"][0]
    assert sample.unit == stats.PATIENT and sample.patients == 3
    # the patient level counts: wider than the same data read as "these patients" (trajectories as units)
    these = stats.interval(sample.as_unit(stats.TRAJECTORY), scale=stats.POSITIVE)
    v = row.values[0]
    assert isinstance(v, Estimate) and v.has_interval
    assert v.hi - v.lo > 2 * (these[1] - these[0])


def test_cross_subject_with_two_patients_shows_means_only_and_says_why():
    t = cross_subject(_cross_sweep(patients=("p00", "p01")).context(), "pair")
    assert "resting on 2 patients (p00, p01): too few to measure how patients differ" in t.caption
    models = [i for i, r in enumerate(t.rows) if r.kind == "model"]
    assert all(isinstance(v, Estimate) and not v.has_interval for i in models for v in t.rows[i].values)
    assert not any(mk for i in models for mk in t.marks[i])  # no best, tie or †
    assert not t.skill


def test_personalized_caption_states_these_patients():
    m = _clustered()
    for seed in (0, 1, 2):
        m.add("lstm", "ce", seed=seed)
    t = personalized(m.context(), "pair")
    assert "for new seeds and new test trajectories of these 3 patients (p00, p01, p02), not a new patient" in \
        t.caption
    assert t.rows[0].info["samples"][0].unit == stats.TRAJECTORY


def test_two_seeds_are_read_for_their_trained_models_not_for_new_seeds():
    """Two seeds cannot measure how seeds differ: the interval is the one-replicate interval of the seeds'
    per-trajectory mean errors (the trained models, seeds fixed), not a new-seeds interval."""
    rng = np.random.default_rng(0)
    keys = tuple(("p00", "ur", f"t{i}") for i in range(12))
    w = rng.integers(10, 60, 12).astype(float)
    errors = rng.lognormal(0.5, 0.3, (2, 12)) + np.array([[0.0], [0.8]])  # two seeds that differ a lot
    two = stats.Sample(keys, w, errors)
    averaged = stats.Sample(keys, w, errors.mean(0, keepdims=True))
    assert two.seeds_fixed and not stats.refusal(two)
    assert two.mean == pytest.approx(averaged.mean)
    for scale in (stats.POSITIVE, stats.LINEAR):
        assert stats.interval(two, scale=scale) == pytest.approx(stats.interval(averaged, scale=scale))
    three = stats.Sample(keys, w, np.vstack([errors, errors[:1] + 0.4]))  # three seeds: the seed spread counts
    lo3, hi3 = stats.interval(three, scale=stats.LINEAR)
    lo1, hi1 = stats.interval(stats.Sample(keys, w, three.errors.mean(0, keepdims=True)), scale=stats.LINEAR)
    assert not three.seeds_fixed and hi3 - lo3 > hi1 - lo1


def test_two_seeds_show_intervals_and_marks_about_their_trained_models():
    m = MemRuns(seed=4)
    for seed in (0, 1):
        m.add("lstm", "ce", (2.0, 10.0, 0.10, 0.010), seed=seed)
        m.add("convlstm", "ce", (6.0, 30.0, 0.30, 0.030), seed=seed)  # worse than the references
    t = personalized(m.context(), "accumulated")
    models = [i for i, r in enumerate(t.rows) if r.kind == "model"]
    runs = {r.run_id: r for r in m.records}
    for i in models:
        reps = replicates([runs[x] for x in t.rows[i].runs])
        logged = np.mean([np.mean([r.metrics["acc.pos_l2.mean"] for r in rep]) for rep in reps])
        v = t.rows[i].values[0]
        assert v.mean == pytest.approx(logged) and v.has_interval and v.lo < v.mean < v.hi
    worse = next(i for i, r in enumerate(t.rows) if r.group == "+ConvRNN")
    # the † rule applies to the trained models: worse than the training mean in position and rotation (6.0 vs 5.8,
    # 30 vs 23), better in DE and CE (0.30 vs 0.34, 0.030 vs 0.072)
    assert ["noskill" in mk for mk in t.marks[worse]] == [True, True, False, False]
    assert "about the trained models of each row (2 seeds, fixed: not new seeds" in t.caption
    assert not any("Means only" in n for n in t.notes)
    refs = [r for r in t.rows if r.kind == "reference"]
    assert all(v.has_interval for r in refs for v in r.values)


def test_a_third_seed_brings_the_interval_and_the_marks_back():
    m = MemRuns(seed=4)
    for seed in (0, 1, 2):
        m.add("lstm", "ce", (2.0, 10.0, 0.10, 0.010), seed=seed)
        m.add("convlstm", "ce", (6.5, 30.0, 0.40, 0.090), seed=seed)
    t = personalized(m.context(), "accumulated")
    assert not any("Means only" in n for n in t.notes)
    assert all(v.has_interval for r in t.rows for v in r.values)
    worse = next(i for i, r in enumerate(t.rows) if r.group == "+ConvRNN")
    assert all("noskill" in mk for mk in t.marks[worse])


def test_tracking_table_keeps_a_near_zero_ctf_interval_inside_0_100():
    """Zero motion tracks almost nothing (CTF ~ 0 %, a few trajectories a few %): the linear t interval would
    reach below 0; the logit one stays in [0, 100]. A near-perfect model's CTF near 100 % stays below 100."""
    m = MemRuns(seed=5, keys=[("p00", lobe, f"{lobe}0") for lobe in ("ur", "br", "ul", "bl")])
    for key, h in zip(m.keys, (0.5, 1.2, 1.3, 1.4)):  # one easy trajectory: zero motion tracks a few % of it
        m.hard[key]["acc"] = h
    refs = {"zero_motion": (22.0, 80.0, 0.5, 0.1), "train_mean": (20.0, 70.0, 0.4, 0.09)}
    for seed in (0, 1, 2):
        m.add("lstm", "ce", (0.02, 0.05, 0.001, 0.0001), seed=seed, refs=refs, noise=0.3)
    t = tracking(m.context(), "accumulated")
    ctf_cols = [j for j, c in enumerate(t.columns) if c.title.startswith("CTF")]
    assert [t.columns[j].title for j in ctf_cols] == ["CTF mm", "CTF vox"]  # mm is the primary column
    zero = next(r for r in t.rows if r.label == "Zero motion")
    model = next(r for r in t.rows if r.kind == "model")
    frames = m.context().frames(m.records)
    linear = stats.interval(reference_sample(m.records, frames, "zero_motion", "trajectory", "ctf"))
    assert linear[0] < 0.0  # what the plain interval did
    for j in ctf_cols:
        v = zero.values[j]
        assert 0.0 <= v.lo <= v.mean <= v.hi <= 100.0 and v.mean < 5.0
        w = model.values[j]
        assert 0.0 <= w.lo <= w.mean <= w.hi <= 100.0 and w.mean > 99.0


def test_positive_errors_keep_their_interval_above_zero():
    base = np.array([0.010, 0.020, 0.015, 0.500, 0.012, 0.011, 0.018, 0.014])  # one hard trajectory
    errors = base * np.array([[1.0], [1.1], [0.9]])
    s = stats.Sample(tuple(("p", "l", f"t{i}") for i in range(8)), np.ones(8), errors)
    lin = stats.interval(s, scale=stats.LINEAR)
    pos = stats.interval(s, scale=stats.POSITIVE)
    assert lin[0] < 0.0 < pos[0] <= s.mean <= pos[1]
    assert pos[1] - s.mean > s.mean - pos[0]  # longer upwards: the errors are right-skewed
    one = stats.Sample(s.keys[:1], np.ones(1), errors[:1, :1])
    assert math.isnan(stats.interval(one, scale=stats.POSITIVE)[0])  # one seed, one trajectory: nothing measured


def _keys(n: int):
    return tuple(("p", "l", f"t{i}") for i in range(n))


def test_an_all_zero_percentage_gets_an_honest_upper_bound_and_no_warning():
    import warnings

    zero = stats.Sample(_keys(12), np.ones(12), np.zeros((3, 12)))
    full = stats.Sample(_keys(12), np.ones(12), np.full((3, 12), 100.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the RuntimeWarning of the earlier [0, 0]
        lo, hi = stats.interval(zero, scale=stats.PERCENT)
        assert lo == 0.0 and hi == pytest.approx(100 * (1 - 0.025 ** (1 / 12)))  # 26.5 %, not 0
        assert stats.interval(full, scale=stats.PERCENT) == (pytest.approx(100 - hi), 100.0)
        assert all(math.isnan(x) for x in stats.interval(zero, scale=stats.POSITIVE))  # an error of 0: no width
        assert stats.paired_p(zero, zero) == 1.0


def test_errors_with_exact_zeros_stay_on_the_log_scale():
    # ATE-type: some trajectories have error 0 in every seed, the others are right-skewed. The interval is the
    # shifted-log one (stats.zeros_interval), not the linear fallback: above 0, longer upwards, the mean inside.
    rng = np.random.default_rng(4)
    errors = np.exp(1.0 * rng.standard_normal((1, 16))) * np.exp(0.1 * rng.standard_normal((3, 1)))
    errors[:, :4] = 0.0
    s = stats.Sample(_keys(16), np.ones(16), errors)
    lo, hi = stats.interval(s, scale=stats.POSITIVE)
    c = stats.ZERO_SHIFT * s.mean
    ref = stats.positive_interval(errors + c, np.ones(16))
    assert (lo, hi) == (pytest.approx(max(float(ref[0]) - c, 0.0)), pytest.approx(float(ref[1]) - c))
    assert 0.0 <= lo < s.mean < hi and hi - s.mean > s.mean - lo
    lin = stats.interval(s, scale=stats.LINEAR)
    assert hi > lin[1]  # longer upwards than the linear interval where zeros and a long right tail meet


def test_one_seed_states_its_estimand_once():
    m = MemRuns(seed=21)
    m.add("lstm", "ce", (2.0, 10.0, 0.10, 0.010), seed=0)
    m.add("convlstm", "ce", (2.3, 11.0, 0.11, 0.011), seed=0)
    t = personalized(m.context(), "accumulated")
    assert "about the one trained model of each row (one seed, not new seeds)" in t.caption
    assert "new seeds and new test trajectories" not in t.caption and not any("one seed" in n for n in t.notes)
    for seed in (1, 2):
        m.add("convlstm", "ce", (2.3, 11.0, 0.11, 0.011), seed=seed)
    t = personalized(m.context(), "accumulated")
    assert "for new seeds and new test trajectories of these" in t.caption
    assert "Rows with one seed (+LSTM MSE+CE): about that one trained model" in t.notes[0]


def test_the_tracking_caption_counts_frames():
    m = MemRuns(seed=22)
    for seed in (0, 1, 2):
        m.add("lstm", "ce", (2.0, 10.0, 0.10, 0.010), seed=seed)
    t = tracking(m.context(), "accumulated")
    assert "pairs)" not in t.caption and re.search(r"× \d+ test trajectories \(\d+ scored frames\)", t.caption)


def test_rows_at_different_precisions_are_named_in_a_note_with_one_warning():
    import dataclasses

    m = MemRuns(seed=23)
    for seed in (0, 1, 2):
        m.add("offsetnet", "mse", (5.0, 20.0, 0.3, 0.05), seed=seed)
        m.add("convlstm", "ce", (2.3, 11.0, 0.11, 0.011), seed=seed)
    m.records = [dataclasses.replace(r, params={"speed.precision": "bf16-mixed" if r.tags["arch"] == "offsetnet"
                                                else "32"}) for r in m.records]
    from bronchocli.reporting.tables import sota

    t = sota(m.context(), "accumulated")
    note = next(n for n in t.notes if n.startswith("Numerics differ between rows ("))
    assert "OffsetNet: bf16 autocast" in note and ": fp32" in note and "Numerics" not in t.caption
    assert [w for w in t.warnings if "different precisions" in w] == [
        "table6-sota-accumulated: rows trained at different precisions (bf16 autocast, fp32): the table's note "
        "names each row's; set train.precision in the config to compare at equal numerics"]
    m.records = [dataclasses.replace(r, params={"speed.precision": "32"}) for r in m.records]
    t = sota(m.context(), "accumulated")
    assert "Numerics: every row trained at fp32." in t.source and not any("Numerics" in n for n in t.notes)
    assert not [w for w in t.warnings if "precision" in w]
