"""Calibration of the report's intervals and paired test at few seeds, by simulation with known true means.

    python benchmarks/bench_calibration.py [--experiments 2000] [--trajectories 12] [--seeds 3 5] [--baseline 400]
                                           [--pair-weights]

Each simulated experiment is one table cell (and, for the test, two rows on the
same test trajectories): ``error[r, t] = mu + seed_r + shared_t + own_t + noise_rt``
with seeds independent per row, trajectory difficulty ``shared_t`` common to
the two rows (what the pairing cancels), a row-specific trajectory effect
``own_t`` and per-(seed, trajectory) noise. Regimes (standard deviations):

* seed-dominated:       seed 1.0, trajectory 0.3 (shared 0.27, own 0.13), noise 0.3;
* mixed:                seed 0.5, trajectory 0.5 (shared 0.45, own 0.22), noise 0.5;
* trajectory-dominated: seed 0.1, trajectory 1.0 (shared 0.89, own 0.45), noise 0.5.

The true mean is mu (over new seeds and new trajectories). Measured per regime
and seed count, with the report's own functions (``stats.combine``, which
``stats.interval`` and ``stats.paired_p`` call):

* coverage: share of experiments whose 95 % interval holds mu;
* false-positive rate: share of 'equal means' pairs the paired test calls
  different at alpha 0.05 (both rows the same mu);
* power: the same when the second row's mean is one seed-SD higher.

``--pair-weights`` weights the trajectories by unequal pair counts (10-59, as
the per-pair tables do) instead of equally (the accumulated tables).
``--baseline N`` (default 400 experiments; 0 skips it) also measures the procedure the report used
before (two-level percentile bootstrap, 2,000 resamples, reimplemented here)
and a seed-level t interval on per-seed means (2 df at 3 seeds), for
comparison. The last line is ``min coverage <x>, max false-positive rate <y>``
over every regime and seed count of the report's procedure.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats as sps

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bronchocli.reporting.stats import ALPHA, combine  # noqa: E402

SHARED = 0.8  # share of the trajectory variance common to the two rows of a comparison
REGIMES = {  # seed SD, trajectory SD, noise SD
    "seed-dominated": (1.0, 0.3, 0.3),
    "mixed": (0.5, 0.5, 0.5),
    "trajectory-dominated": (0.1, 1.0, 0.5),
}
MU = 10.0


def simulate(rng: np.random.Generator, n: int, seeds: int, trajectories: int, sd: tuple[float, float, float],
             shift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Two rows ``(n, seeds, trajectories)`` on shared trajectories; the second row's mean is ``MU + shift``."""
    s_seed, s_traj, s_noise = sd
    shared = rng.standard_normal((n, 1, trajectories)) * s_traj * np.sqrt(SHARED)

    def row(mean: float) -> np.ndarray:
        own = rng.standard_normal((n, 1, trajectories)) * s_traj * np.sqrt(1.0 - SHARED)
        seed = rng.standard_normal((n, seeds, 1)) * s_seed
        noise = rng.standard_normal((n, seeds, trajectories)) * s_noise
        return mean + shared + own + seed + noise

    return row(MU), row(MU + shift)


def report_procedure(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lo, hi) of row a and the paired p of a vs b: the report's code, batched."""
    lo, hi = combine([a], w, [1.0]).interval()
    return lo, hi, combine([a, b], w, [1.0, -1.0]).p


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


def measure(procedure, rng: np.random.Generator, n: int, seeds: int, trajectories: int,
            sd: tuple[float, float, float], w: np.ndarray | None = None) -> dict[str, float]:
    w = np.ones(trajectories) if w is None else w
    a, b = simulate(rng, n, seeds, trajectories, sd)
    lo, hi, p = procedure(a, b, w)
    a2, b2 = simulate(rng, n, seeds, trajectories, sd, shift=sd[0])
    _, _, p_power = procedure(a2, b2, w)
    return {"coverage": float(np.mean((lo <= MU) & (MU <= hi))), "fpr": float(np.mean(p < ALPHA)),
            "power": float(np.mean(p_power < ALPHA)), "width": float(np.median(hi - lo))}


def run(experiments: int, trajectories: int, seed_counts, baseline: int = 0, seed: int = 1,
        pair_weights: bool = False) -> dict:
    """{(procedure, seeds, regime): measures}; ``baseline`` > 0: also the two alternatives, on that many."""
    w = pair_counts(trajectories) if pair_weights else None
    procedures = {"report": (report_procedure, experiments)}
    if baseline:
        procedures |= {"seed-level t": (seed_t, baseline), "old bootstrap": (old_bootstrap, baseline)}
    results = {}
    for name, (proc, n) in procedures.items():
        for seeds in seed_counts:
            for regime, sd in REGIMES.items():
                rng = np.random.default_rng([seed, seeds, list(REGIMES).index(regime)])
                results[(name, seeds, regime)] = measure(proc, rng, n, seeds, trajectories, sd, w)
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiments", type=int, default=2000,
                    help="simulated experiments per regime and seed count (Monte Carlo SE of a 0.95 coverage: 0.005)")
    ap.add_argument("--trajectories", type=int, default=12)
    ap.add_argument("--seeds", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--baseline", type=int, default=400, metavar="N",
                    help="experiments for the two alternatives (old bootstrap, seed-level t); 0 skips them")
    ap.add_argument("--pair-weights", action="store_true",
                    help="weight the trajectories by unequal pair counts (the per-pair tables)")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    results = run(args.experiments, args.trajectories, args.seeds, args.baseline, pair_weights=args.pair_weights)
    print(f"{args.experiments} experiments per row of the report's procedure ({args.baseline} for the others), "
          f"{args.trajectories} test trajectories ({'weighted by pairs' if args.pair_weights else 'equal weights'}), "
          f"alpha {ALPHA:g}; "
          f"power = detection of a difference of one seed-SD")
    print("| procedure | seeds | regime | coverage | false-positive rate | power | median width |")
    print("|---|---:|---|---:|---:|---:|---:|")
    for (name, seeds, regime), m in results.items():
        print(f"| {name} | {seeds} | {regime} | {m['coverage']:.3f} | {m['fpr']:.3f} | {m['power']:.3f} | "
              f"{m['width']:.2f} |")
    ours = [m for (name, _, _), m in results.items() if name == "report"]
    print(f"({time.perf_counter() - start:.1f} s)")
    print(f"min coverage {min(m['coverage'] for m in ours):.3f}, "
          f"max false-positive rate {max(m['fpr'] for m in ours):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
