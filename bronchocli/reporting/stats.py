"""The statistics behind every table cell: variance components over seeds and test trajectories, t intervals.

A cell's data is a :class:`Sample`: for each replicate (a seed; for
cross-subject the fold runs of one seed together) the per-trajectory error of
every shared test trajectory, and each trajectory's weight (its number of
pairs for per-pair metrics, 1 for accumulated ones). Its value is the mean over
replicates of the weighted mean over trajectories, i.e. the mean of the
run-level metric the runs logged.

What a 95 % interval must cover is the mean over *new* seeds and *new* test
trajectories, so both sources of variation count. With R seeds, T
trajectories (normalised weights w) and the model
``error[r, t] = mu + seed_r + traj_t + noise_rt``, the variance of a linear
combination ``sum_i c_i mean_i`` of cells sharing their trajectories is
estimated from moments (no resampling, exact and fast):

* a **seed part** per cell, ``c^2 var_r(seed mean_r) / R`` (R - 1 df), minus
  its noise share ``c^2 sum(w^2) MS_noise / R`` (the noise is counted again in
  the trajectory part), truncated at 0;
* one **trajectory part** for the combination, the weighted variance of the
  per-trajectory combination ``sum_i c_i trajmean_i[t]`` (T - 1 df; trajectory
  difficulty shared by the cells cancels here — that is the pairing);

and the t quantile uses Satterthwaite's degrees of freedom, computed with the
seed parts at their median-unbiased value (``_median_unbiased``). With 3 seeds and
seed-to-seed variation dominating that is about 2 df (t = 4.3): wide, but
calibrated. ``benchmarks/bench_calibration.py`` simulates the three regimes
(seed-dominated, mixed, trajectory-dominated) at 3 and 5 seeds and measures
coverage, the false-positive rate of ``paired_p`` and its power; the figures
are in docs/reports.md. A cell with one replicate (or a reference, which does
not depend on the seed) has no seed part: its interval covers the trajectory
variation only.

* ``interval``: the t interval of one sample's mean;
* ``paired_p``: two rows on their shared trajectories (seeds independent per
  row), a Welch-Satterthwaite t test of equal means, two-sided;
* ``derived`` / ``skill``: a smooth function of several means (skill =
  1 - error / reference error) by the delta method on the same components;
* ``holm``: Holm's step-down adjustment of a family of p-values.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy import stats as sps

ALPHA = 0.05
LEVEL = 0.95
Key = tuple[str, str, str]  # (patient, lobe, trajectory)
METHOD = ("t interval with variance components over seeds and test trajectories (Satterthwaite df)")


@dataclass(frozen=True)
class Sample:
    """Per-trajectory errors of one cell: ``errors[r, t]`` for replicate r and trajectory ``keys[t]``."""

    keys: tuple[Key, ...]
    weights: np.ndarray  # (T,) n_pairs (per-pair metrics) or ones (accumulated)
    errors: np.ndarray  # (R, T)
    pairs: int = 0  # test pairs behind the T trajectories

    def __post_init__(self) -> None:
        if self.errors.ndim != 2 or self.errors.shape[1] != len(self.keys) or len(self.weights) != len(self.keys):
            raise ValueError(f"errors {self.errors.shape} do not match {len(self.keys)} keys / weights")

    @property
    def replicates(self) -> int:
        return int(self.errors.shape[0])

    @property
    def trajectories(self) -> int:
        return len(self.keys)

    @property
    def mean(self) -> float:
        return float(np.mean(self.errors @ self.weights / self.weights.sum()))

    def restricted(self, keys: Sequence[Key]) -> "Sample":
        """The same sample on ``keys`` (a subset of its own), in that order."""
        pos = {k: i for i, k in enumerate(self.keys)}
        idx = np.array([pos[k] for k in keys], dtype=int)
        return Sample(tuple(keys), self.weights[idx], self.errors[:, idx], self.pairs)


def common_keys(samples: Sequence[Sample]) -> list[Key]:
    """The trajectories every sample has, sorted (what a comparison is computed on)."""
    keys = set(samples[0].keys)
    for s in samples[1:]:
        keys &= set(s.keys)
    return sorted(keys)


# ---------------------------------------------------------------- array core (batched; the benchmark calls it)

@dataclass(frozen=True)
class Inference:
    """A linear combination of cell means: value, standard error and Satterthwaite df (arrays or floats)."""

    value: np.ndarray
    se: np.ndarray
    df: np.ndarray

    def interval(self, level: float = LEVEL) -> tuple[np.ndarray, np.ndarray]:
        half = sps.t.ppf(0.5 + level / 2.0, self.df) * self.se
        return self.value - half, self.value + half

    @property
    def p(self) -> np.ndarray:
        """Two-sided p of 'the combination is 0' (1 when the value and its standard error are 0, or when no
        variation can be measured at all: one seed and one trajectory)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.abs(self.value) / self.se
        t = np.where(self.se > 0, t, np.where(self.value == 0, 0.0, np.inf))
        return np.where(np.isnan(self.se), 1.0, 2.0 * sps.t.sf(t, np.nan_to_num(self.df, nan=1.0)))


def _satterthwaite(terms: Sequence[tuple[np.ndarray, float]], for_df: Sequence[np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Sum of variance terms and Satterthwaite's df, (sum v)^2 / sum(v^2 / df), from ``for_df`` (the terms as
    the df sees them)."""
    total = sum(v for v, _ in terms)
    seen = sum(for_df)
    denom = sum(v * v / df for v, (_, df) in zip(for_df, terms))
    with np.errstate(divide="ignore", invalid="ignore"):
        df = np.where(denom > 0, seen * seen / denom, np.inf)
    return total, df


def _median_unbiased(v: np.ndarray, df: np.ndarray) -> np.ndarray:
    """A variance estimate with ``df`` degrees of freedom scaled to its median-unbiased value (chi2 median).

    Satterthwaite's df is liberal when a few-df seed part happens to come out small (the df then jumps to the
    trajectory part's, exactly when the interval is too short); computing the df from the median-unbiased seed
    variance (x 1.44 at 2 df) removes that (bench_calibration: coverage 0.931 -> 0.941 at 3 seeds, seed-dominated).
    """
    return v * df / sps.chi2.ppf(0.5, df)


def _seed_part(errors: np.ndarray, w: np.ndarray, coef: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``c^2 sigma_seed^2 / R`` of one cell (``errors (..., R, T)``) and its df; None with one replicate."""
    r, t = errors.shape[-2:]
    if r < 2:
        return None
    seed_means = errors @ w  # (..., R)
    v_seed = coef ** 2 * seed_means.var(-1, ddof=1) / r
    sw2 = float(np.sum(w * w))
    traj_means = errors.mean(-2)  # (..., T)
    resid = errors - seed_means[..., :, None] - traj_means[..., None, :] + (seed_means.mean(-1))[..., None, None]
    ms_noise = (resid ** 2 @ w).sum(-1) / ((r - 1) * max(1.0 - sw2, 1e-12))
    v_noise = coef ** 2 * sw2 * ms_noise / r  # the noise share, also in the trajectory part
    part = np.maximum(v_seed - v_noise, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = v_seed ** 2 / (r - 1) + v_noise ** 2 / ((r - 1) * max(t - 1, 1))
        df = np.where(denom > 0, part ** 2 / denom, np.inf)
    return part, np.maximum(df, 1.0)


def combine(errors: Sequence[np.ndarray], weights: np.ndarray, coefs: Sequence) -> Inference:
    """Inference on ``sum_i coefs[i] * mean_i``, the cells ``errors[i] (..., R_i, T)`` on the same T trajectories.

    Leading dimensions are a batch (independent experiments); ``coefs`` may be arrays of that batch shape.
    """
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    t = len(w)
    coefs = [np.asarray(c, dtype=np.float64) for c in coefs]
    value = sum(c * (e @ w).mean(-1) for c, e in zip(coefs, errors))
    per_traj = sum(c[..., None] * e.mean(-2) for c, e in zip(coefs, errors))  # (..., T)
    terms: list[tuple[np.ndarray, float]] = []
    for_df: list[np.ndarray] = []
    if t > 1:
        centred = per_traj - (per_traj @ w)[..., None]
        v_traj = t / (t - 1) * (centred ** 2 @ (w * w))
        n_eff = 1.0 / float(np.sum(w * w))
        terms.append((v_traj, max(n_eff - 1.0, 1.0)))
        for_df.append(v_traj)
    for c, e in zip(coefs, errors):
        part = _seed_part(e, w, c)
        if part is not None:
            terms.append(part)  # type: ignore[arg-type]
            for_df.append(_median_unbiased(*part))
    if not terms:  # one replicate of one trajectory: no variation to measure
        nan = np.full_like(np.asarray(value, dtype=np.float64), np.nan)
        return Inference(np.asarray(value), nan, nan)
    total, df = _satterthwaite(terms, for_df)
    return Inference(np.asarray(value), np.sqrt(np.maximum(total, 0.0)), df)


# ---------------------------------------------------------------- on samples (what the tables call)

def _aligned(samples: Sequence[Sample]) -> list[Sample]:
    keys = common_keys(samples)
    if not keys:
        raise ValueError("the samples share no test trajectory")
    return [s.restricted(keys) for s in samples]


def linear(samples: Sequence[Sample], coefs: Sequence[float]) -> Inference:
    """Inference on ``sum_i coefs[i] * mean_i`` over the samples' shared trajectories."""
    aligned = _aligned(samples)
    return combine([s.errors for s in aligned], aligned[0].weights, coefs)


def interval(sample: Sample, level: float = LEVEL) -> tuple[float, float]:
    """The t interval of the sample's mean (seed and trajectory variation, Satterthwaite df); NaN bounds when
    nothing varies that could be measured (one replicate, one trajectory)."""
    inf = combine([sample.errors], sample.weights, [1.0])
    lo, hi = inf.interval(level)
    return float(lo), float(hi)


def paired_p(a: Sample, b: Sample) -> float:
    """Two-sided test of equal means of ``a`` and ``b`` on their shared trajectories (seeds independent)."""
    return float(linear([a, b], [1.0, -1.0]).p)


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm step-down adjusted p-values, in the input order."""
    p = np.asarray(pvalues, dtype=np.float64)
    m = len(p)
    order = np.argsort(p, kind="stable")
    adjusted = np.minimum(1.0, np.maximum.accumulate((m - np.arange(m)) * p[order]))
    out = np.empty(m)
    out[order] = adjusted
    return out.tolist()


@dataclass(frozen=True)
class Derived:
    """A statistic of several samples with its interval (e.g. a skill) and the p of 'it is 0'."""

    value: float
    lo: float
    hi: float
    p: float
    df: float


def _gradient(fn: Callable[..., float], point: np.ndarray) -> np.ndarray:
    """Central differences of ``fn`` at ``point`` (the statistics here are ratios: smooth, cheap)."""
    grad = np.empty(len(point))
    for i, x in enumerate(point):
        h = 1e-6 * max(abs(x), 1e-12)
        up, down = point.copy(), point.copy()
        up[i] += h
        down[i] -= h
        grad[i] = (fn(*up) - fn(*down)) / (2.0 * h)
    return grad


def derived(samples: Sequence[Sample], fn: Callable[..., float], level: float = LEVEL) -> Derived:
    """``fn(*means)`` with its delta-method t interval: ``fn``'s gradient as the coefficients of ``linear``."""
    aligned = _aligned(samples)
    point = np.array([s.mean for s in aligned])
    value = float(fn(*point))
    inf = linear(aligned, _gradient(fn, point).tolist())
    half = float(sps.t.ppf(0.5 + level / 2.0, inf.df) * inf.se)
    p = float(Inference(np.asarray(value), inf.se, inf.df).p)
    return Derived(value, value - half, value + half, p, float(inf.df))


def skill(model: Sample, reference: Sample, level: float = LEVEL) -> Derived:
    """1 - model error / reference error (0: no better than the reference; 1: perfect)."""
    return derived([model, reference], lambda m, r: 1.0 - m / r, level)
