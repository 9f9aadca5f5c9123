"""Calibration of the report's intervals and paired test, by simulation with known true means.

    python benchmarks/bench_calibration.py [--experiments 10000] [--trajectories 12] [--regimes NAME ...]
                                           [--baseline 400] [--ties 1000] [--pair-weights]
    python benchmarks/bench_calibration.py --check-docs   # exit 1 when docs/reports.md's block differs

Each simulated experiment is one table cell (and, for the test, two rows on the
same test trajectories):

    error[r, t] = mu + seed_r + patient_p(t) + (seed x patient)_r,p(t) + traj_t + noise_rt

seeds independent per row; the patient effect and 80 % of the trajectory
effect shared by the two rows of a comparison (a hard patient or trajectory is
hard for every model: what the pairing cancels); the seed x patient
interaction row-specific. Regimes (standard deviations; T = 12 trajectories,
split as evenly as possible over the patients):

| regime | seed | patient | seed x patient | trajectory | noise | seeds |
|---|---|---|---|---|---|---|
| seed-dominated | 1.0 | - | - | 0.3 | 0.3 | 3, 5 |
| mixed | 0.5 | - | - | 0.5 | 0.5 | 3, 5 |
| trajectory-dominated | 0.1 | - | - | 1.0 | 0.5 | 3, 5 |
| 3 patients / 5 patients | 0.5 | 0.8 | - | 0.5 | 0.5 | 3, 5 |
| lognormal seeds | 1.0, lognormal | - | - | 0.3 | 0.3 | 3, 5 |
| lognormal trajectories | 0.1 | - | - | 1.0, lognormal | 0.5 | 3, 5 |
| seed x patient, 3 / 5 patients | 0.3 | 0.5 | 0.8 | 0.5 | 0.5 | 3, 5 |
| lognormal patients, 3 / 5 patients | 0.5 | 1.0, lognormal | - | 0.5 | 0.5 | 3, 5 |
| lognormal trajectories, 20 % zeros | 0.1 | - | - | 1.0, lognormal | 0.5 | 3, 5 |
| 2 seeds | 0.5 | - | - | 0.5 | 0.5 | 2 |
| shifted lognormal seeds (not graded) | 1.0, shifted | - | - | 0.3 | 0.3 | 3, 5 |

"lognormal" = a standardised lognormal with sigma 1 (skewness 6.2) scaled to
the SD: positive, right-skewed errors (where seeds dominate this is the same,
up to location and scale, as a multiplicative lognormal seed factor), except
in "shifted lognormal seeds", where it is an additive effect; a lognormal
patient or trajectory level is a multiplicative factor of mean 1 with that
sigma. "20 % zeros": a fifth of the trajectories have an error of exactly 0 for
every row and seed.

Two estimands, each scored by the procedure the report uses for it
(the interval of a positive figure, ``stats.positive_interval`` -- Cox's
lognormal-mean interval, ``stats.zeros_interval`` where some errors are 0 --
and the paired test ``stats.combine(...).p``, on the trajectories or on the
patient means, ``stats.collapse``):

* **these patients** (personalized tables): the mean over new seeds and new
  trajectories of the simulated patients, mu + their patients' mean effect;
* **a new patient** (cross-subject tables): mu, the mean over new patients too.
  Only in regimes with patients;
* **these trained models** (any table, rows with fewer than ``stats.MIN_SEEDS``
  seeds: ``Sample.seeds_fixed``): the mean over new test trajectories of these
  patients of the models trained with the seeds drawn, mu + their patients'
  mean effect + the drawn seeds' mean effect (and interaction). The interval
  is the report's on the seeds' per-trajectory mean errors. Its coverage is
  scored; its test compares two rows' trained models, so the null of equal new-
  seed means is not its null: no false-positive rate or power (``—``). Only at 2 seeds.

Measured per regime, seed count and estimand: coverage (share of 95 %
intervals holding the estimand), false-positive rate (share of equal-mean
pairs the paired test calls different at alpha 0.05), power (the same when the
second row is one seed-SD worse) and the median width. Where the report prints
no interval for an estimand (new seeds at 2 seeds, a new patient with fewer
than ``stats.MIN_PATIENTS`` patients) the row
says ``refused`` and shows, for the record, what the plain procedure would
have given. ``old: trajectories for a new patient`` is the previous report's
procedure (trajectories as units) scored against a new patient: the blind spot
the patient level fixes. ``--baseline N`` also runs the two procedures the
report used before (two-level percentile bootstrap, seed-level t) on the three
original regimes. ``--ties N`` measures the tied group (``stats.tied_with_best``)
of 3, 6 and 12 truly equal rows. ``--check-docs`` runs the defaults and
compares the block it prints with docs/reports.md's (between the
``bench_calibration`` markers). The last line is ``min coverage <x>, max false-positive rate
<y>`` over every row where the report prints an interval (``KNOWN_SHORT`` rows,
none now, would be named after it instead).

10,000 experiments per row: the Monte Carlo SE of a coverage near the 0.93
bound is 0.0026. At 2,000 (SE 0.0057) the row "lognormal patients, 3 patients,
5 seeds, a new patient" printed 0.929, below the bound; its coverage is 0.938,
0.936 and 0.934 at 20,000 experiments with three simulation seeds (0.932,
0.932, 0.936 at 3 seeds): the interval is not short there, 2,000 experiments
could not tell a row 0.006 above the bound from one below it (issue 36).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import stats as sps

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import docblocks  # noqa: E402

from bronchocli.reporting.stats import (  # noqa: E402
    ALPHA,
    MIN_PATIENTS,
    MIN_SEEDS,
    collapse,
    combine,
    holm_array,
    positive_interval,
    tied_with_best,
)

SHARED = 0.8  # share of the trajectory variance common to the two rows of a comparison
MU = 10.0
SKEW_SIGMA = 1.0  # sigma of the lognormal effects (skewness 6.2)


@dataclass(frozen=True)
class Regime:
    seed: float
    traj: float
    noise: float
    patients: int = 0  # 0: no patient level
    patient: float = 0.0
    interaction: float = 0.0  # seed x patient
    seed_skew: str = ""  # "lognormal": a multiplicative lognormal seed factor (sigma = seed); "shifted": additive
    traj_skew: str = ""  # "lognormal": a multiplicative lognormal trajectory factor (sigma = traj)
    patient_skew: str = ""  # "lognormal": a multiplicative lognormal patient factor (sigma = patient)
    zeros: float = 0.0  # share of trajectories whose error is exactly 0 for every row and seed (an ATE-type 0)
    seeds: tuple[int, ...] = (3, 5)


BASE = {"seed-dominated": Regime(1.0, 0.3, 0.3), "mixed": Regime(0.5, 0.5, 0.5),
        "trajectory-dominated": Regime(0.1, 1.0, 0.5)}
REGIMES = {
    **BASE,
    "3 patients": Regime(0.5, 0.5, 0.5, patients=3, patient=0.8),
    "5 patients": Regime(0.5, 0.5, 0.5, patients=5, patient=0.8),
    "lognormal seeds": replace(BASE["seed-dominated"], seed_skew="lognormal"),
    "lognormal trajectories": replace(BASE["trajectory-dominated"], traj_skew="lognormal"),
    "seed x patient, 3 patients": Regime(0.3, 0.5, 0.5, patients=3, patient=0.5, interaction=0.8),
    "seed x patient, 5 patients": Regime(0.3, 0.5, 0.5, patients=5, patient=0.5, interaction=0.8),
    "lognormal patients, 3 patients": Regime(0.5, 0.5, 0.5, patients=3, patient=1.0, patient_skew="lognormal"),
    "lognormal patients, 5 patients": Regime(0.5, 0.5, 0.5, patients=5, patient=1.0, patient_skew="lognormal"),
    "lognormal trajectories, 20 % zeros": replace(BASE["trajectory-dominated"], traj_skew="lognormal", zeros=0.2),
    "2 seeds": replace(BASE["mixed"], seeds=(2,)),
    "shifted lognormal seeds": replace(BASE["seed-dominated"], seed_skew="shifted"),
}
UNGRADED = {"shifted lognormal seeds"}  # beyond what 3-5 seeds can show (docs/reports.md): measured, not graded
# Rows below the 0.93 bound that no interval tried so far fixes: kept out of the graded minimum, printed on a line
# of their own, and held to KNOWN_SHORT_FLOOR by the tests so that they cannot get worse unseen. None: the one
# listed before (lognormal patients, 3 patients, 5 seeds, a new patient: 0.929 at 2,000 experiments) covers
# 0.934-0.938 at 20,000 with three simulation seeds; it was Monte Carlo error at 2,000 (the module's docstring).
KNOWN_SHORT: set[tuple[int, str, str]] = set()
KNOWN_SHORT_FLOOR = 0.92


def _effect(rng: np.random.Generator, shape: tuple[int, ...], sd: float, shifted: bool = False) -> np.ndarray:
    """Normal effects with SD ``sd``; ``shifted``: a standardised lognormal (sigma 1) scaled to ``sd``."""
    if not shifted:
        return rng.standard_normal(shape) * sd
    s = SKEW_SIGMA
    z = np.exp(s * rng.standard_normal(shape))
    return (z - np.exp(s * s / 2)) / np.sqrt((np.exp(s * s) - 1) * np.exp(s * s)) * sd


def _factor(z: np.ndarray, sigma: float) -> np.ndarray:
    """A lognormal factor with mean 1 from standard normal ``z``."""
    return np.exp(sigma * z - sigma * sigma / 2.0)


def groups_of(trajectories: int, patients: int) -> np.ndarray:
    """The patient of each trajectory: as even a split as possible (12 over 5: 3, 3, 2, 2, 2)."""
    return np.arange(trajectories) % patients if patients else np.zeros(trajectories, dtype=int)


@dataclass
class Experiments:
    a: np.ndarray  # (n, R, T)
    b: np.ndarray
    these: np.ndarray  # (n,) row a's mean over these patients (new seeds and trajectories)
    fixed: np.ndarray  # (n,) row a's mean over new trajectories of these patients, its drawn seeds fixed


def simulate(rng: np.random.Generator, n: int, seeds: int, trajectories: int, g: Regime, shift: float = 0.0,
             w: np.ndarray | None = None) -> Experiments:
    """Two rows ``(n, seeds, trajectories)``; the second row's mean is ``MU + shift``."""
    (a, b), these, fixed = simulate_rows(rng, n, seeds, trajectories, g, (0.0, shift), w, conditional=True)
    return Experiments(a, b, these, fixed)


def simulate_rows(rng: np.random.Generator, n: int, seeds: int, trajectories: int, g: Regime,
                  shifts: tuple[float, ...], w: np.ndarray | None = None, conditional: bool = False):
    """Rows ``(n, seeds, trajectories)`` of one table column on the same test trajectories, row i's mean
    ``MU + shifts[i]``; and the first row's mean over these patients; ``conditional``: also the first row's
    mean with its drawn seeds fixed (over new trajectories and noise: these trained models)."""
    groups = groups_of(trajectories, g.patients)
    w = np.ones(trajectories) if w is None else w
    shared_z = rng.standard_normal((n, 1, trajectories)) * np.sqrt(SHARED)
    patient = _effect(rng, (n, 1, max(g.patients, 1)), g.patient)[..., groups]
    if g.patient_skew == "lognormal":  # the patient level is the factor; its additive effect is not drawn again
        patient_factor = _factor(patient / g.patient, g.patient)
        patient = np.zeros_like(patient)

    keep = (rng.random((n, 1, trajectories)) >= g.zeros) if g.zeros else np.ones((1, 1, 1), dtype=bool)

    wn = w / w.sum()
    given: list[np.ndarray] = []  # per row: its expected error with its seeds fixed, averaged over them (n,)

    def row(mean: float) -> np.ndarray:
        errors, expected = parts(mean)
        given.append((expected.mean(-2) @ wn) * (1.0 - g.zeros))
        return errors * keep

    def parts(mean: float) -> tuple[np.ndarray, np.ndarray]:
        """The errors and their expectation over new trajectories and noise (traj_z and noise have mean 0,
        a lognormal factor mean 1)."""
        traj_z = shared_z + rng.standard_normal((n, 1, trajectories)) * np.sqrt(1.0 - SHARED)
        seed = _effect(rng, (n, seeds, 1), g.seed, g.seed_skew == "shifted")
        inter = _effect(rng, (n, seeds, max(g.patients, 1)), g.interaction)[..., groups]
        noise = rng.standard_normal((n, seeds, trajectories)) * g.noise
        if g.seed_skew == "lognormal":  # errors = (mean + the other parts) x a seed factor of mean 1
            f = _factor(seed / g.seed, g.seed)
            return (mean + traj_z * g.traj + patient + inter + noise) * f, (mean + patient + inter) * f
        if g.traj_skew == "lognormal":
            base = mean + patient + seed + inter
            return (base + noise) * _factor(traj_z, g.traj), base
        if g.patient_skew == "lognormal":  # errors = (mean + the other parts) x a patient factor of mean 1
            return ((mean + traj_z * g.traj + seed + inter + noise) * patient_factor,
                    (mean + seed + inter) * patient_factor)
        return mean + traj_z * g.traj + patient + seed + inter + noise, mean + patient + seed + inter

    level = MU * patient_factor[:, 0, :] if g.patient_skew == "lognormal" else MU + patient[:, 0, :]
    these = (level @ wn) * (1.0 - g.zeros)
    rows = [row(MU + x) for x in shifts]
    return (rows, these, given[0]) if conditional else (rows, these)


TIE_ROWS = (3, 6, 12)  # rows of a column (Table 6: 2; Tables 2/3: 12)
TIE_REGIMES = ("mixed", "seed-dominated", "trajectory-dominated")


def tied_group(rng: np.random.Generator, n: int, seeds: int, trajectories: int, g: Regime, k: int,
               w: np.ndarray | None = None) -> dict[str, float]:
    """k truly equal rows of a column: the share of experiments in which the report's tied group (the best by
    mean, Holm over every pair: ``stats.tied_with_best``) leaves one of them out, and the same for the previous
    rule (Holm over best vs each other row only)."""
    w = np.ones(trajectories) if w is None else w
    rows, _ = simulate_rows(rng, n, seeds, trajectories, g, (0.0,) * k, w)
    means = np.stack([(x @ (w / w.sum())).mean(-1) for x in rows], -1)
    pair_p = np.ones((n, k, k))
    for i in range(k):
        for j in range(i + 1, k):
            pair_p[:, i, j] = pair_p[:, j, i] = combine([rows[i], rows[j]], w, [1.0, -1.0]).p
    _, _, tied = tied_with_best(means, pair_p)
    best = np.argmin(means, -1)
    vs_best = np.take_along_axis(pair_p, best[:, None, None], 1)[:, 0, :]
    others = np.where(np.arange(k) == best[:, None], np.inf, vs_best)  # the best itself sorts last
    old = holm_array(np.sort(others, -1)[:, : k - 1])  # Holm over the k - 1 comparisons with the best
    return {"report": float(np.mean(~tied.all(-1))), "old": float(np.mean((old < ALPHA).any(-1)))}


def run_ties(experiments: int, trajectories: int, seed: int = 1, w: np.ndarray | None = None) -> dict:
    """{(seeds, regime, k): tied_group(...)} over TIE_REGIMES x TIE_ROWS at 3 and 5 seeds."""
    out = {}
    for name in TIE_REGIMES:
        for seeds in (3, 5):
            for k in TIE_ROWS:
                rng = np.random.default_rng([seed, seeds, k, list(REGIMES).index(name), 7])
                out[(seeds, name, k)] = tied_group(rng, experiments, seeds, trajectories, REGIMES[name], k, w)
    return out


FIXED = "these trained models"  # the estimand of rows with fewer than MIN_SEEDS seeds (Sample.seeds_fixed)


def _units(x: np.ndarray, w: np.ndarray, patients: int, unit: str) -> tuple[np.ndarray, np.ndarray]:
    if unit == "fixed":  # the seeds' mean error per trajectory: one replicate (Sample.units with seeds_fixed)
        return x.mean(-2, keepdims=True), w
    if unit == "trajectory":
        return x, w
    return collapse(x, w, groups_of(x.shape[-1], patients), patients)


def report_procedure(a: np.ndarray, b: np.ndarray, w: np.ndarray, patients: int = 0, unit: str = "trajectory"
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lo, hi) of row a (positive figure) and the paired p of a vs b: the report's code, batched."""
    (ua, wu), (ub, _) = _units(a, w, patients, unit), _units(b, w, patients, unit)
    lo, hi = positive_interval(ua, wu)
    return lo, hi, combine([ua, ub], wu, [1.0, -1.0]).p


def seed_t(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate: t interval on the per-seed means (R - 1 df); Welch test on per-seed means."""
    ma, mb = a @ (w / w.sum()), b @ (w / w.sum())
    r = ma.shape[-1]
    se = ma.std(-1, ddof=1) / np.sqrt(r)
    q = sps.t.ppf(0.975, r - 1)
    p = sps.ttest_ind(ma, mb, axis=-1, equal_var=False).pvalue
    return ma.mean(-1) - q * se, ma.mean(-1) + q * se, p


def old_bootstrap(a: np.ndarray, b: np.ndarray, w: np.ndarray, resamples: int = 2000
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The previous procedure: two-level percentile bootstrap (trajectories jointly, seeds per row)."""
    rng = np.random.default_rng(20240614)
    n, r, t = a.shape
    lo, hi, p = np.empty(n), np.empty(n), np.empty(n)

    def counts(k: int) -> np.ndarray:
        idx = rng.integers(0, k, size=(resamples, k)) + (np.arange(resamples) * k)[:, None]
        return np.bincount(idx.ravel(), minlength=resamples * k).reshape(resamples, k).astype(float)

    for i in range(n):
        cw = counts(t) * w
        boot = []
        for x in (a[i], b[i]):
            per_rep = (cw @ x.T) / cw.sum(1, keepdims=True)
            boot.append((counts(r) * per_rep).sum(1) / r)
        lo[i], hi[i] = np.percentile(boot[0], [2.5, 97.5])
        d = boot[0] - boot[1]
        below = (np.count_nonzero(d <= 0) + 1) / (resamples + 1)
        above = (np.count_nonzero(d >= 0) + 1) / (resamples + 1)
        p[i] = min(1.0, 2.0 * min(below, above))
    return lo, hi, p


def pair_counts(trajectories: int) -> np.ndarray:
    return np.random.default_rng(0).integers(10, 60, trajectories).astype(float)


def _scores(lo, hi, p, p_power, target) -> dict[str, float]:
    return {"coverage": float(np.mean((lo <= target) & (target <= hi))), "fpr": float(np.mean(p < ALPHA)),
            "power": float(np.mean(p_power < ALPHA)), "width": float(np.median(hi - lo))}


def printed(seeds: int, patients: int, estimand: str) -> bool:
    """Whether the report prints an interval and marks for this design and estimand (stats.refusal; below
    MIN_SEEDS seeds it prints the trained models' interval, never a new-seeds one)."""
    if estimand == FIXED:
        return seeds < MIN_SEEDS
    return not (1 < seeds < MIN_SEEDS) and not (estimand == "a new patient" and patients < MIN_PATIENTS)


def measure(rng: np.random.Generator, n: int, seeds: int, trajectories: int, g: Regime,
            w: np.ndarray | None = None) -> dict[str, dict[str, float]]:
    """{estimand: scores} of the report's procedures in one regime and seed count."""
    w = np.ones(trajectories) if w is None else w
    null, alt = (simulate(rng, n, seeds, trajectories, g, shift, w) for shift in (0.0, g.seed))
    out = {}
    plans = [("these patients", "trajectory", null.these)]
    if g.patients:
        plans += [("a new patient", "patient", np.full(n, MU)), ("old: trajectories for a new patient",
                                                                 "trajectory", np.full(n, MU))]
    for estimand, unit, target in plans:
        lo, hi, p = report_procedure(null.a, null.b, w, g.patients, unit)
        _, _, p_power = report_procedure(alt.a, alt.b, w, g.patients, unit)
        out[estimand] = _scores(lo, hi, p, p_power, target)
    if seeds < MIN_SEEDS:  # the interval the report prints: the trained models' (coverage only, module doc)
        lo, hi, _ = report_procedure(null.a, null.b, w, 0, "fixed")
        out[FIXED] = {**_scores(lo, hi, np.ones(n), np.ones(n), null.fixed), "fpr": float("nan"),
                      "power": float("nan")}
    return out


def run(experiments: int, trajectories: int, regimes=None, baseline: int = 0, seed: int = 1,
        pair_weights: bool = False) -> dict:
    """{(procedure, seeds, regime, estimand): scores}; ``baseline`` > 0: also the two alternatives on the three
    original regimes, on that many experiments."""
    w = pair_counts(trajectories) if pair_weights else None
    names = list(REGIMES) if regimes is None else list(regimes)
    results = {}
    for name in names:
        g = REGIMES[name]
        for seeds in g.seeds:
            rng = np.random.default_rng([seed, seeds, list(REGIMES).index(name)])
            for estimand, m in measure(rng, experiments, seeds, trajectories, g, w).items():
                results[("report", seeds, name, estimand)] = m
    if baseline:
        for proc_name, proc in (("seed-level t", seed_t), ("old bootstrap", old_bootstrap)):
            for name in [x for x in BASE if x in names]:
                for seeds in BASE[name].seeds:
                    rng = np.random.default_rng([seed, seeds, list(REGIMES).index(name)])
                    null, alt = (simulate(rng, baseline, seeds, trajectories, BASE[name], s, w)
                                 for s in (0.0, BASE[name].seed))
                    ww = np.ones(trajectories) if w is None else w
                    lo, hi, p = proc(null.a, null.b, ww)
                    results[(proc_name, seeds, name, "these patients")] = _scores(
                        lo, hi, p, proc(alt.a, alt.b, ww)[2], null.these)
    return results


def graded(results: dict) -> list[dict[str, float]]:
    """The report's rows that print an interval (what the acceptance bounds apply to)."""
    return [m for (proc, seeds, name, est), m in results.items()
            if proc == "report" and not est.startswith("old") and name not in UNGRADED
            and (seeds, name, est) not in KNOWN_SHORT and printed(seeds, REGIMES[name].patients, est)]


def known_short(results: dict) -> dict[tuple[int, str, str], dict[str, float]]:
    """The KNOWN_SHORT rows that were simulated, by (seeds, regime, estimand)."""
    return {(seeds, name, est): m for (proc, seeds, name, est), m in results.items()
            if proc == "report" and (seeds, name, est) in KNOWN_SHORT}


def _both(values: list[float], fmt: str) -> str:
    return " / ".join(format(v, fmt) for v in values)


def docs_table(results: dict, ties: dict) -> list[str]:
    """The calibration tables of docs/reports.md, as the benchmark prints them (``--check-docs`` compares)."""
    lines = ["| seeds | regime | estimand | coverage | FPR | power (1 seed-SD) | median width |",
             "|---:|---|---|---:|---:|---:|---:|"]
    groups: dict[tuple[str, str], list[tuple[int, dict]]] = {}
    for (proc, seeds, name, est), m in results.items():
        if proc == "report":
            groups.setdefault((name, est), []).append((seeds, m))
    for (name, est), got in groups.items():
        seeds = " / ".join(str(x) for x, _ in got)
        ms = [m for _, m in got]
        regime = name + (" (not graded)" if name in UNGRADED else "")
        if est.startswith("old"):
            lines.append(f"| {seeds} | {regime} | *{est}* | {_both([m['coverage'] for m in ms], '.3f')} | | | |")
        elif est == FIXED:
            lines.append(f"| {seeds} | {regime} | {est} | {_both([m['coverage'] for m in ms], '.3f')} | — | — | "
                         f"{_both([m['width'] for m in ms], '.3g')} |")
        elif not printed(got[0][0], REGIMES[name].patients, est):
            lines.append(f"| {seeds} | {regime} | {est} | refused (would be {_both([m['coverage'] for m in ms], '.3f')})"
                         f" | refused ({_both([m['fpr'] for m in ms], '.3f')}) | | |")
        else:
            lines.append(f"| {seeds} | {regime} | {est} | {_both([m['coverage'] for m in ms], '.3f')} | "
                         f"{_both([m['fpr'] for m in ms], '.3f')} | {_both([m['power'] for m in ms], '.3f')} | "
                         f"{_both([m['width'] for m in ms], '.3g')} |")
    if ties:
        lines += ["", "| seeds | regime | rows (all equal) | a truly equal row left out of the tied group | "
                  "previous rule (Holm over best vs others) |", "|---:|---|---:|---:|---:|"]
        for (seeds, name, k), m in ties.items():
            lines.append(f"| {seeds} | {name} | {k} | {m['report']:.3f} | {m['old']:.3f} |")
    lines += ["", summary(results, ties)]
    return lines


def summary(results: dict, ties: dict) -> str:
    ours = graded(results)
    fpr = [m["fpr"] for m in ours if m["fpr"] == m["fpr"]] + [m["report"] for m in ties.values()]
    short = "".join(f"; known shortfall (issue 36 open): {name}, {seeds} seeds, {est}: coverage {m['coverage']:.3f}"
                    for (seeds, name, est), m in known_short(results).items())
    return (f"min coverage {min(m['coverage'] for m in ours):.3f}, "
            f"max false-positive rate {max(fpr):.3f}{short}")


RESULT = "calibration"  # benchmarks/results/calibration.json: docs/reports.md's block is rendered from it (docblocks)
COMMAND = "python benchmarks/bench_calibration.py --record"


def check_docs(lines: list[str], results_dir: Path = docblocks.RESULTS) -> list[str]:
    """The lines where the recorded calibration tables (results/calibration.json, which docs/reports.md's block
    shows: docblocks checks that) differ from ``lines`` (empty: they agree)."""
    path = results_dir / f"{RESULT}.json"
    try:
        recorded = docblocks.load_results(results_dir)[RESULT]["figures"]["docs_table"]
    except KeyError:
        return [f"{path}: no recorded calibration tables (run {COMMAND})"]
    return [f"recorded: {a!r}\nbench: {b!r}" for a, b in zip(recorded + [""] * len(lines), lines + [""] * len(recorded))
            if a.strip() != b.strip()]


def record_results(results: dict, ties: dict, experiments: int, seconds: float,
                   results_dir: Path = docblocks.RESULTS) -> Path:
    """results/calibration.json from a run at the defaults; docs/reports.md's block and the Summary row follow
    with ``python benchmarks/docblocks.py --write``."""
    ours = graded(results)
    fpr = [m["fpr"] for m in ours if m["fpr"] == m["fpr"]] + [m["report"] for m in ties.values()]
    cov, worst = min(m["coverage"] for m in ours), max(fpr)
    return docblocks.record(
        RESULT, title="Calibration of the report's 95 % intervals and paired test", command=COMMAND,
        machine=docblocks.machine() + " (a simulation with fixed seeds: the figures do not depend on the machine)",
        cpu="any (simulation)", results_dir=results_dir,
        summary={"figure": "calibration of the report's 95 % intervals and paired test, every regime and estimand "
                           "the report prints (docs/reports.md)",
                 "result": f"**min coverage {cov:.3f}, max false-positive rate {worst:.3f}**",
                 "goal": "coverage ≥ 0.93, FPR ≤ 0.06 " + ("✔" if cov >= 0.93 and worst <= 0.06 else "✘")},
        figures={"experiments_per_row": experiments, "seconds": round(seconds, 1), "min_coverage": round(cov, 3),
                 "max_fpr": round(worst, 3), "docs_table": docs_table(results, ties)})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiments", type=int, default=10000,
                    help="simulated experiments per regime and seed count (Monte Carlo SE of a 0.93 coverage: "
                         "0.0026)")
    ap.add_argument("--trajectories", type=int, default=12)
    ap.add_argument("--regimes", nargs="+", choices=list(REGIMES), default=None, metavar="NAME",
                    help=f"regimes to run (default all): {', '.join(REGIMES)}")
    ap.add_argument("--baseline", type=int, default=400, metavar="N",
                    help="experiments for the two earlier procedures (old bootstrap, seed-level t); 0 skips them")
    ap.add_argument("--ties", type=int, default=1000, metavar="N",
                    help="experiments per tied-group row (k truly equal rows of a column); 0 skips them")
    ap.add_argument("--pair-weights", action="store_true",
                    help="weight the trajectories by unequal pair counts (the per-pair tables)")
    ap.add_argument("--check-docs", action="store_true",
                    help="run with the defaults and exit 1 when the recorded tables (results/calibration.json, "
                         "shown in docs/reports.md) differ")
    ap.add_argument("--record", action="store_true",
                    help="run with the defaults and write results/calibration.json (then: docblocks.py --write)")
    args = ap.parse_args(argv)
    if args.check_docs or args.record:
        start = time.perf_counter()
        defaults = ap.parse_args([])
        results = run(defaults.experiments, defaults.trajectories, None, 0)
        ties = run_ties(defaults.ties, defaults.trajectories)
        if args.record:
            path = record_results(results, ties, defaults.experiments, time.perf_counter() - start)
            print(f"wrote {path}; now `python benchmarks/docblocks.py --write` regenerates docs/reports.md's block")
            return 0
        diff = check_docs(docs_table(results, ties))
        for line in diff:
            print(line)
        print("results/calibration.json matches the benchmark" if not diff else f"{len(diff)} line(s) of "
              f"results/calibration.json differ from the benchmark: record it again ({COMMAND})")
        return 1 if diff else 0
    start = time.perf_counter()
    results = run(args.experiments, args.trajectories, args.regimes, args.baseline, pair_weights=args.pair_weights)
    w = pair_counts(args.trajectories) if args.pair_weights else None
    ties = run_ties(args.ties, args.trajectories, w=w) if args.ties else {}
    print(f"{args.experiments} experiments per row of the report's procedure ({args.baseline} for the others, "
          f"{args.ties} per tied-group row), {args.trajectories} test trajectories "
          f"({'weighted by pairs' if args.pair_weights else 'equal weights'}), "
          f"alpha {ALPHA:g}; power = detection of a difference of one seed-SD")
    print("| procedure | seeds | regime | estimand | coverage | false-positive rate | power | median width |")
    print("|---|---:|---|---|---:|---:|---:|---:|")
    for (proc, seeds, name, est), m in results.items():
        shown = proc != "report" or est.startswith("old") or printed(seeds, REGIMES[name].patients, est)
        cells = f"{m['coverage']:.3f} | {m['fpr']:.3f} | {m['power']:.3f} | {m['width']:.2f}"
        if not shown:
            cells = " | ".join(f"refused ({x})" for x in cells.split(" | "))
        print(f"| {proc} | {seeds} | {name} | {est} | {cells} |")
    print("\nThe block of docs/reports.md (recorded with --record):\n")
    print("\n".join(docs_table(results, ties)))
    print(f"({time.perf_counter() - start:.1f} s)")
    print(summary(results, ties))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
