"""The bootstrap, the paired test and Holm's correction, against independent references."""

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


def test_one_seed_many_trajectories_interval_matches_the_normal_approximation():
    rng = np.random.default_rng(1)
    x = rng.gamma(4.0, 0.5, 400)
    lo, hi = stats.interval(_sample(x))
    half = 1.96 * x.std(ddof=1) / math.sqrt(len(x))
    assert lo == pytest.approx(x.mean() - half, abs=0.1 * half)
    assert hi == pytest.approx(x.mean() + half, abs=0.1 * half)


def test_one_seed_interval_matches_scipy_percentile_bootstrap():
    rng = np.random.default_rng(2)
    x = rng.lognormal(0.0, 0.5, 60)
    lo, hi = stats.interval(_sample(x))
    ref = sps.bootstrap((x,), np.mean, n_resamples=20000, method="percentile", random_state=3).confidence_interval
    half = (ref.high - ref.low) / 2
    assert lo == pytest.approx(ref.low, abs=0.08 * half) and hi == pytest.approx(ref.high, abs=0.08 * half)


def test_weighted_mean_is_the_mean_over_pairs():
    # Per-trajectory mean errors weighted by their pairs = the mean over all pairs.
    pairs = [np.full(3, 1.0), np.full(7, 2.0), np.full(10, 4.0)]
    s = _sample([[p.mean() for p in pairs]], [len(p) for p in pairs])
    assert s.mean == pytest.approx(np.concatenate(pairs).mean())


def _naive_two_level(errors: np.ndarray, weights: np.ndarray, draws: int, seed: int) -> np.ndarray:
    """A loop implementation of the two-level bootstrap (seeds and trajectories with replacement)."""
    rng = np.random.default_rng(seed)
    r, t = errors.shape
    out = np.empty(draws)
    for b in range(draws):
        traj = rng.integers(0, t, t)
        reps = rng.integers(0, r, r)
        out[b] = np.mean([np.sum(weights[traj] * errors[k, traj]) / weights[traj].sum() for k in reps])
    return out


def test_two_level_spread_matches_a_loop_implementation():
    rng = np.random.default_rng(4)
    t, r = 30, 3
    hard = rng.lognormal(0, 0.3, t)
    errors = hard * (1 + 0.2 * rng.standard_normal((r, t))) + 0.3 * rng.standard_normal((r, 1))
    weights = rng.integers(5, 30, t).astype(float)
    _, boot = stats.joint_means([_sample(errors, weights)], resamples=4000)
    naive = _naive_two_level(errors, weights, 4000, 5)
    assert boot[:, 0].std() == pytest.approx(naive.std(), rel=0.08)
    assert boot[:, 0].mean() == pytest.approx(naive.mean(), abs=0.1 * naive.std())


def test_seed_resampling_widens_the_interval():
    rng = np.random.default_rng(6)
    base = rng.lognormal(0, 0.2, 40)
    calm = np.stack([base * 1.0, base * 1.0, base * 1.0])
    shaky = np.stack([base * 0.8, base * 1.0, base * 1.2])  # same mean, seeds disagree
    lo_c, hi_c = stats.interval(_sample(calm))
    lo_s, hi_s = stats.interval(_sample(shaky))
    assert (hi_s - lo_s) > 1.5 * (hi_c - lo_c)


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


def test_two_sided_p_counts_both_tails():
    assert stats.two_sided_p(np.full(999, 1.0)) == pytest.approx(2 / 1000)
    assert stats.two_sided_p(np.r_[np.full(900, 1.0), np.full(99, -1.0)]) == pytest.approx(2 * 100 / 1000)


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
