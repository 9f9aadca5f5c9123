"""From runs to samples: replicates, per-trajectory tables, references and the logged-mean fallback."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from bronchocli.reporting.aggregate import RunErrors, logged_mean, model_sample, reference_sample, replicates
from bronchocli.reporting.collect import RunRecord


def _run(run_id: str, seed: int = 0, fold: str = "", **metrics: float) -> RunRecord:
    return RunRecord(run_id, "FINISHED", 0, {"seed": str(seed), "fold": fold}, metrics)


def _errors(patient: str, values: list[float], pairs: list[int], zero: list[float] | None = None) -> RunErrors:
    df = pd.DataFrame({"patient": patient, "lobe": "ur", "trajectory": [str(i) for i in range(len(values))],
                       "n_pairs": pairs, "model.pair.pos_l2": values, "model.acc.pos_l2": values,
                       "zero_motion.pair.pos_l2": zero or values, "zero_motion.acc.pos_l2": zero or values})
    return RunErrors.from_frame(df)


def test_replicates_group_runs_by_seed_in_numeric_order():
    runs = [_run("a", 10, "p00"), _run("b", 2, "p00"), _run("c", 10, "p01")]
    assert [[r.run_id for r in rep] for rep in replicates(runs)] == [["b"], ["a", "c"]]


def test_pair_sample_weights_trajectories_by_their_pairs():
    frames = {"a": _errors("p00", [1.0, 4.0], [1, 3])}
    pair = model_sample([[_run("a")]], frames, "pair", "pos_l2")
    acc = model_sample([[_run("a")]], frames, "accumulated", "pos_l2")
    assert pair.mean == pytest.approx((1 * 1.0 + 3 * 4.0) / 4) and pair.pairs == 4
    assert acc.mean == pytest.approx(2.5)


def test_a_cross_subject_replicate_joins_its_folds_and_replicates_share_trajectories():
    frames = {"s0p0": _errors("p00", [1.0, 2.0], [2, 2]), "s0p1": _errors("p01", [3.0], [4]),
              "s1p0": _errors("p00", [1.5, 2.5], [2, 2]), "s1p1": _errors("p01", [3.5], [4])}
    reps = replicates([_run(k, int(k[1]), "p0" + k[3]) for k in frames])
    s = model_sample(reps, frames, "pair", "pos_l2")
    assert s.replicates == 2 and s.trajectories == 3
    per_seed = [(2 * 1.0 + 2 * 2.0 + 4 * 3.0) / 8, (2 * 1.5 + 2 * 2.5 + 4 * 3.5) / 8]
    assert s.mean == pytest.approx(np.mean(per_seed))


def test_a_run_without_its_errors_table_gives_no_sample():
    assert model_sample([[_run("a")]], {"a": None}, "pair", "pos_l2") is None
    assert model_sample([[_run("a")]], {"a": _errors("p00", [1.0], [1])}, "pair", "ce") is None  # no such column


def test_references_average_each_trajectory_over_the_runs_that_have_it():
    frames = {"a": _errors("p00", [9.0, 9.0], [1, 1], zero=[1.0, 3.0]),
              "b": _errors("p00", [9.0, 9.0], [1, 1], zero=[2.0, 5.0])}
    ref = reference_sample([_run("a"), _run("b")], frames, "zero_motion", "accumulated", "pos_l2")
    assert ref.replicates == 1 and ref.errors.tolist() == [[1.5, 4.0]]


def test_logged_mean_fallback_weights_folds_by_their_test_counts():
    reps = [[_run("a", 0, "p00", **{"acc.ce.mean": 3.0, "test.n_trajectories": 4}),
             _run("b", 0, "p01", **{"acc.ce.mean": 5.0, "test.n_trajectories": 6})],
            [_run("c", 1, "p00", **{"acc.ce.mean": 1.0, "test.n_trajectories": 4}),
             _run("d", 1, "p01", **{"acc.ce.mean": 1.0, "test.n_trajectories": 6})]]
    assert logged_mean(reps, "accumulated", "ce") == pytest.approx((4.2 + 1.0) / 2)
    assert logged_mean(reps, "pair", "ce") is None  # not logged
    no_count = [[_run("a", 0, "p00", **{"acc.ce.mean": 3.0}), _run("b", 0, "p01", **{"acc.ce.mean": 5.0})]]
    assert logged_mean(no_count, "accumulated", "ce") is None  # folds cannot be weighted
