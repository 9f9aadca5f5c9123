"""Pooling per-run statistics: against a hand computation and against numpy on the raw samples."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bronchocli.metrics import Stat
from bronchocli.reporting.aggregate import cell_value, pooled, run_stat
from bronchocli.reporting.collect import RunRecord


def test_pooled_matches_a_hand_computation():
    # fold A: 4 values, mean 3, std 1; fold B: 6 values, mean 5, std 2.
    # N = 10, mean = (12 + 30) / 10 = 4.2; E[x^2] = (4 (1 + 9) + 6 (4 + 25)) / 10 = 21.4;
    # var = 21.4 - 4.2^2 = 3.76.
    s = pooled([Stat(3.0, 1.0, 4), Stat(5.0, 2.0, 6)])
    assert s.n == 10
    assert s.mean == pytest.approx(4.2)
    assert s.std == pytest.approx(math.sqrt(3.76))


@pytest.mark.parametrize("seed", range(5))
def test_pooled_equals_the_statistics_of_the_concatenated_samples(seed):
    rng = np.random.default_rng(seed)
    parts = [rng.gamma(2.0, rng.uniform(0.5, 3.0), rng.integers(1, 40)) for _ in range(rng.integers(2, 6))]
    s = pooled([Stat(float(p.mean()), float(p.std()), len(p)) for p in parts])
    every = np.concatenate(parts)
    assert s.n == every.size
    assert s.mean == pytest.approx(every.mean(), rel=1e-12)
    assert s.std == pytest.approx(every.std(ddof=0), rel=1e-9)


def test_a_single_run_is_passed_through_and_nothing_to_pool_is_an_error():
    assert pooled([Stat(1.0, 0.5, 0)]) == Stat(1.0, 0.5, 0)
    with pytest.raises(ValueError):
        pooled([])


def test_cell_value_pools_with_the_test_counts_of_each_run():
    a = RunRecord("a", "FINISHED", 0, {}, {"acc.ce.mean": 3.0, "acc.ce.std": 1.0, "test.n_trajectories": 4})
    b = RunRecord("b", "FINISHED", 0, {}, {"acc.ce.mean": 5.0, "acc.ce.std": 2.0, "test.n_trajectories": 6})
    cell = cell_value([a, b], "ce", "accumulated")
    assert cell.runs == ("a", "b") and cell.stat.mean == pytest.approx(4.2)
    assert run_stat(a, "ce", "pair") is None  # per-pair metrics were not logged


def test_cell_value_explains_what_is_missing():
    a = RunRecord("a", "FINISHED", 0, {}, {"pair.de.mean": 1.0, "pair.de.std": 0.1})
    b = RunRecord("b", "FINISHED", 0, {}, {"pair.de.mean": 2.0, "pair.de.std": 0.1, "test.n_pairs": 5})
    assert cell_value([a], "de", "pair").stat == Stat(1.0, 0.1, 0)  # one run needs no count
    pooled_cell = cell_value([a, b], "de", "pair")
    assert pooled_cell.stat is None and "run a has no test.n_pairs" in pooled_cell.problem
    missing = cell_value([b], "ce", "pair")
    assert missing.stat is None and "pair.ce.mean" in missing.problem
