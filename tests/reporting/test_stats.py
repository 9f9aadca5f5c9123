"""Intervals, the paired test, skill and Holm's correction, against independent references (SciPy, ANOVA by hand)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as sps

from bronchocli.reporting import stats
from bronchocli.reporting.stats import Sample


def _sample(errors: np.ndarray, weights: np.ndarray | None = None, prefix: str = "t") -> Sample:
    errors = np.atleast_2d(np.asarray(errors, dtype=float))
    t = errors.shape[1]
    keys = tuple(("p", "l", f"{prefix}{i:04d}") for i in range(t))
    return Sample(keys, np.ones(t) if weights is None else np.asarray(weights, float), errors)


def test_one_seed_interval_is_the_t_interval_over_trajectories():
    rng = np.random.default_rng(1)
    x = rng.gamma(4.0, 0.5, 40)
    lo, hi = stats.interval(_sample(x))
    ref = sps.t.interval(0.95, len(x) - 1, loc=x.mean(), scale=sps.sem(x))
    assert (lo, hi) == pytest.approx(ref, rel=1e-12)


def test_weighted_mean_is_the_mean_over_pairs():
    # Per-trajectory mean errors weighted by their pairs = the mean over all pairs.
    pairs = [np.full(3, 1.0), np.full(7, 2.0), np.full(10, 4.0)]
    s = _sample([[p.mean() for p in pairs]], [len(p) for p in pairs])
    assert s.mean == pytest.approx(np.concatenate(pairs).mean())


def _anova_variance(y: np.ndarray) -> float:
    """Two-way random-effects ANOVA by sums of squares: var(grand mean) = (MS_seed + MS_traj - MS_res) / (R T)."""
    r, t = y.shape
    g = y.mean()
    ms_seed = t * ((y.mean(1) - g) ** 2).sum() / (r - 1)
    ms_traj = r * ((y.mean(0) - g) ** 2).sum() / (t - 1)
    res = y - y.mean(1, keepdims=True) - y.mean(0, keepdims=True) + g
    ms_res = (res ** 2).sum() / ((r - 1) * (t - 1))
    return (ms_seed + ms_traj - ms_res) / (r * t)


def test_balanced_variance_is_the_two_way_anova_estimate():
    rng = np.random.default_rng(4)
    r, t = 4, 15
    y = 2.0 + rng.standard_normal((r, 1)) + 0.7 * rng.standard_normal((1, t)) + 0.3 * rng.standard_normal((r, t))
    inf = stats.linear([_sample(y)], [1.0])
    assert inf.se ** 2 == pytest.approx(_anova_variance(y), rel=1e-10)
    assert float(inf.value) == pytest.approx(y.mean())
    assert 3.0 <= float(inf.df) <= t - 1 + r - 1  # between the seed part's df and the total


def test_seed_variation_widens_the_interval_to_the_seed_level_t():
    rng = np.random.default_rng(6)
    base = rng.lognormal(0, 0.2, 40)
    calm = np.stack([base * 1.0, base * 1.0, base * 1.0])
    shifts = np.array([[-0.3], [0.0], [0.4]])  # the seeds disagree by a constant: only the seed part grows
    lo_c, hi_c = stats.interval(_sample(calm))
    lo_s, hi_s = stats.interval(_sample(calm + shifts))
    assert (hi_s - lo_s) > 3 * (hi_c - lo_c)
    # dominated by 3 seed means: close to their t interval with 2 df
    ref = sps.t.interval(0.95, 2, loc=(calm + shifts).mean(), scale=sps.sem((calm + shifts).mean(1)))
    assert hi_s - lo_s == pytest.approx(ref[1] - ref[0], rel=0.1)


def test_one_seed_paired_test_is_scipys_paired_t_test():
    rng = np.random.default_rng(7)
    hard = rng.lognormal(0, 0.5, 25)
    a, b = hard * (1 + 0.05 * rng.standard_normal(25)), hard * 1.03 * (1 + 0.05 * rng.standard_normal(25))
    assert stats.paired_p(_sample(a), _sample(b)) == pytest.approx(sps.ttest_rel(a, b).pvalue, rel=1e-9)


def test_paired_test_without_trajectory_variation_is_welchs_test_on_seed_means():
    rng = np.random.default_rng(8)
    base = np.full(10, 3.0)
    a = base + rng.standard_normal((3, 1))
    b = base + 0.5 + 2.0 * rng.standard_normal((3, 1))
    ref = sps.ttest_ind(a.mean(1), b.mean(1), equal_var=False).pvalue
    assert stats.paired_p(_sample(a), _sample(b)) == pytest.approx(ref, rel=1e-9)


def test_paired_test_sees_a_small_shift_that_the_intervals_do_not():
    rng = np.random.default_rng(7)
    hard = rng.lognormal(0, 0.5, 25)  # trajectories differ a lot
    a = _sample(hard * (1 + 0.01 * rng.standard_normal(25)))
    b = _sample(hard * 1.05 * (1 + 0.01 * rng.standard_normal(25)))
    lo_b, _ = stats.interval(b)
    _, hi_a = stats.interval(a)
    assert lo_b < hi_a  # the intervals overlap
    assert stats.paired_p(a, b) < 0.01  # but on the same trajectories b is always worse


def test_paired_test_of_two_rows_with_the_same_mean_is_not_significant():
    rng = np.random.default_rng(8)
    hard = rng.lognormal(0, 0.3, 30)
    a = _sample(hard * (1 + 0.1 * rng.standard_normal(30)))
    b = _sample(hard * (1 + 0.1 * rng.standard_normal(30)))
    assert stats.paired_p(a, b) > 0.05


def test_paired_test_uses_only_the_shared_trajectories():
    a = _sample([[1.0, 2.0, 3.0, 100.0]])
    b = Sample(a.keys[:3], np.ones(3), np.array([[1.0, 2.0, 3.0]]))
    assert stats.paired_p(a, b) == 1.0  # identical on the 3 shared ones; a's 4th trajectory is ignored


def test_holm_by_hand_on_three_comparisons():
    # Sorted 0.01, 0.03, 0.04: 3*0.01 = 0.03; 2*0.03 = 0.06; max(0.06, 1*0.04) = 0.06.
    assert stats.holm([0.04, 0.01, 0.03]) == pytest.approx([0.06, 0.03, 0.06])
    assert stats.holm([0.5, 0.9]) == pytest.approx([1.0, 1.0])  # 2*0.5 = 1.0 caps the larger one too
    assert stats.holm([]) == []


def test_skill_against_the_reference():
    rng = np.random.default_rng(9)
    hard = rng.lognormal(0, 0.3, 40)
    ref = _sample(hard * 4.0)
    model = _sample(hard * (1 + 0.05 * rng.standard_normal(40)))
    d = stats.skill(model, ref)
    assert d.value == pytest.approx(1 - model.mean / ref.mean)
    assert d.lo < d.value < d.hi and d.lo > 0.7  # the shared difficulty cancels: a narrow interval
    # delta method by hand (one seed) on the log-ratio scale: log(m/r) linearised is x_t / m - y_t / r per
    # trajectory; skill = 1 - exp(log ratio)
    x, y = model.errors[0], ref.errors[0]
    lin = x / model.mean - y / ref.mean
    half = sps.t.ppf(0.975, len(x) - 1) * lin.std(ddof=1) / math.sqrt(len(x))
    log_ratio = math.log(model.mean / ref.mean)
    assert (d.lo, d.hi) == pytest.approx((1 - math.exp(log_ratio + half), 1 - math.exp(log_ratio - half)), rel=1e-6)


def test_skill_interval_never_exceeds_one():
    """Skill is bounded above by 1 (a perfect model): a near-perfect, noisy model's interval stays below it,
    where the linear delta method would cross it."""
    rng = np.random.default_rng(10)
    ref = _sample(rng.lognormal(0, 0.3, (3, 6)) * 4.0)
    model = _sample(rng.lognormal(-3.0, 1.5, (3, 6)))
    d = stats.skill(model, ref)
    linear = stats.derived([model, ref], lambda m, r: 1.0 - m / r)
    assert linear.hi > 1.0  # the bound the linear interval breaks
    assert d.lo < d.value < d.hi < 1.0


def test_one_seed_of_one_trajectory_has_no_interval_and_no_significance():
    a, b = _sample([[1.0]]), _sample([[2.0]])
    lo, hi = stats.interval(a)
    assert math.isnan(lo) and math.isnan(hi)
    assert stats.paired_p(a, b) == 1.0  # nothing to measure the noise with: no claim
