"""The report's intervals and paired test are calibrated for the estimand they state (benchmarks/bench_calibration.py).

Every regime of the benchmark (seed-, mixed- and trajectory-dominated variance; 3 and 5 patients; lognormal
seed and trajectory effects; a seed x patient interaction; 2 seeds) is simulated with known true means and
scored with the report's own ``stats`` functions, for both estimands (these patients, a new patient). The small
simulation (400 experiments, fixed seed: deterministic; Monte Carlo SE of a 0.95 coverage ≈ 0.011) must cover
>= 0.90 wherever the report prints an interval; the full one (10,000, SE of a coverage near 0.93 ≈ 0.0026) meets
the acceptance bounds 0.93 / 0.06. docs/reports.md's calibration block is what the benchmark prints (``--check-docs``).
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_calibration.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_calibration", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_calibration"] = module  # its dataclasses resolve their annotations through it
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def test_small_simulation_covers_the_stated_estimand_in_every_regime(bench):
    results = bench.run(400, 12, seed=7)
    graded = bench.graded(results)
    estimands = {est for (_, _, _, est) in results}
    assert {"these patients", "a new patient"} <= estimands
    # 2 seed counts x (3 base + 2 lognormal + 1 with exact zeros + 6 with patients, lognormal patients included,
    # x 2 estimands); bench.KNOWN_SHORT (rows held to their own floor) is empty
    # + the trained models' interval at 2 seeds (coverage only: its test has no equal-means null)
    assert len(graded) == 37 and not bench.KNOWN_SHORT
    for m in graded:
        assert m["coverage"] >= 0.90, m
        assert m["fpr"] <= 0.08 or (math.isnan(m["fpr"]) and math.isnan(m["power"])), m
    assert sum(math.isnan(m["fpr"]) for m in graded) == 1


def test_trajectories_as_units_miss_a_new_patient_and_patients_as_units_do_not(bench):
    """The blind spot the patient level closes: with 3 patients whose difficulty differs, treating the
    trajectories as independent under-covers the mean over new patients."""
    results = bench.run(400, 12, ["3 patients"], seed=3)
    old = results[("report", 5, "3 patients", "old: trajectories for a new patient")]["coverage"]
    new = results[("report", 5, "3 patients", "a new patient")]["coverage"]
    assert old < 0.87 < 0.93 <= new


def test_two_seeds_print_the_trained_models_interval_not_a_new_seeds_one(bench):
    """At 2 seeds the new-seeds interval under-covers, so the report does not print it (stats.MIN_SEEDS); the
    interval it prints is about the trained models (Sample.seeds_fixed) and covers their mean."""
    results = bench.run(2000, 12, ["2 seeds"], seed=5)
    assert not bench.printed(2, 0, "these patients") and bench.printed(2, 0, bench.FIXED)
    assert results[("report", 2, "2 seeds", "these patients")]["coverage"] < 0.92
    fixed = results[("report", 2, "2 seeds", bench.FIXED)]
    assert bench.graded(results) == [fixed] and fixed["coverage"] >= 0.93


@pytest.mark.parametrize("pair_weights", [False, True], ids=["accumulated", "per-pair"])
def test_full_simulation_meets_the_acceptance_bounds(bench, pair_weights):
    results = bench.run(10000, 12, pair_weights=pair_weights)
    for m in bench.graded(results):
        assert m["coverage"] >= 0.93 and (m["fpr"] <= 0.06 or math.isnan(m["fpr"])), m
    for key, m in bench.known_short(results).items():  # below the bound, named in the summary line: not worse
        assert m["coverage"] >= bench.KNOWN_SHORT_FLOOR and m["fpr"] <= 0.06, (key, m)
    # power for one seed-SD grows with seeds where seeds dominate
    assert (results[("report", 5, "seed-dominated", "these patients")]["power"]
            > results[("report", 3, "seed-dominated", "these patients")]["power"])


def test_the_old_bootstrap_fails_where_the_issue_says(bench):
    """The reimplemented previous procedure reproduces the issue's finding (so the simulation can see it)."""
    results = bench.run(150, 12, ["seed-dominated"], baseline=150)
    assert results[("old bootstrap", 3, "seed-dominated", "these patients")]["coverage"] < 0.85
    assert results[("old bootstrap", 3, "seed-dominated", "these patients")]["fpr"] > 0.10


def test_recorded_calibration_is_what_the_benchmark_computes(bench):
    """benchmarks/results/calibration.json (which docs/reports.md's block shows: tests/test_doc_numbers.py checks
    that) equals the benchmark's output at its defaults (what ``bench_calibration.py --check-docs`` runs: 10,000
    experiments per row, 1,000 per tied-group row). Any change to the statistics that moves a printed digit
    fails here until ``--record`` writes the file again."""
    results, ties = bench.run(10000, 12, None, 0), bench.run_ties(1000, 12)
    diff = bench.check_docs(bench.docs_table(results, ties))
    assert not diff, "results/calibration.json differs from bench_calibration.py (run it with --record):\n" + \
        "\n".join(diff)


def test_check_docs_names_a_changed_line_and_a_missing_record(bench, tmp_path):
    """The comparison itself: a digit changed, a row missing, or no results file are all reported; ``--record``'s
    writer produces a file the comparison accepts."""
    lines = ["| a | 0.950 |", "| b | 0.931 |", "", "min coverage 0.931, max false-positive rate 0.050"]
    assert bench.check_docs(lines, tmp_path) == [f"{tmp_path / 'calibration.json'}: no recorded calibration tables "
                                                 f"(run {bench.COMMAND})"]
    bench.docblocks.record("calibration", title="t", machine="m", command="c", figures={"docs_table": lines},
                           results_dir=tmp_path)
    assert bench.check_docs(lines, tmp_path) == []
    assert bench.check_docs(["| a | 0.950 |", "| b | 0.929 |", *lines[2:]], tmp_path)  # one digit differs
    assert bench.check_docs(lines + ["| c | 0.940 |"], tmp_path)  # a row the file lacks
