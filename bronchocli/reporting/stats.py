"""The statistics behind every table cell: variance components over seeds, patients and test trajectories.

A cell's data is a :class:`Sample`: for each replicate (a seed; for
cross-subject the fold runs of one seed together) the per-trajectory error of
every shared test trajectory, and each trajectory's weight (its number of
pairs for per-pair metrics, 1 for accumulated ones). Its value is the mean over
replicates of the weighted mean over trajectories, i.e. the mean of the
run-level metric the runs logged.

**Estimand.** What an interval covers is stated by the sample's ``unit``:

* ``trajectory`` — *these patients*: the mean over new seeds and new test
  trajectories of the same patients (personalized tables). Sources: seeds and
  trajectories;
* ``patient`` — *a new patient*: the mean over new seeds, new patients and new
  trajectories of those patients (cross-subject tables). Patients are a level:
  each trajectory is first averaged into its patient (weights summed), so the
  patient-to-patient variation, the trajectory-within-patient variation and a
  seed x patient interaction all enter through the patient means. With few
  patients the interval is honestly wide (2 df at 3 patients).

With R replicates, U units (trajectories or patients; normalised weights w)
and ``error[r, u] = mu + seed_r + unit_u + noise_ru``, the variance of a linear
combination ``sum_i c_i mean_i`` of cells sharing their units is estimated from
moments (no resampling, exact and fast):

* a **seed part** per cell, ``c^2 var_r(seed mean_r) / R`` (R - 1 df), minus
  its noise share ``c^2 sum(w^2) MS_noise / R`` (the noise is counted again in
  the unit part), truncated at 0;
* one **unit part** for the combination, the weighted variance of the per-unit
  combination ``sum_i c_i unitmean_i[u]`` (U - 1 df with equal weights,
  ``_weighted_df`` otherwise; difficulty shared by the cells cancels here —
  that is the pairing);

and the t quantile uses Satterthwaite's degrees of freedom, computed with the
seed parts at their median-unbiased value (``_median_unbiased``), so a few-df
part that happens to come out small does not also shrink the quantile.

**Too few replicates.** Two seeds (or fewer than ``MIN_PATIENTS`` patients for
a new-patient estimand) give no interval and no test (``refusal``): simulated,
they under-cover (0.89) and over-reject. One seed keeps an interval, over the
units only (its estimand is that one trained model; captions say so).

**Scales** (``interval(..., scale=)``): ``linear`` is the plain t interval;
``positive`` (errors: > 0, right-skewed) is Cox's lognormal-mean interval on
the variance parts of the log errors (``positive_interval``: above 0, longer
upwards where a bad seed or a hard trajectory skews the errors, the t interval
where they vary little); ``percent`` (CTF) is the t interval on the logit
scale (inside [0, 100]).
``benchmarks/bench_calibration.py`` measures all of it; the figures are in
docs/reports.md.

* ``interval``: the interval of one sample's mean;
* ``paired_p``: two rows on their shared units (seeds independent per row), a
  Welch-Satterthwaite t test of equal means, two-sided;
* ``skill``: 1 - error / reference error with its interval on the log-ratio
  scale (so it stays <= 1); ``derived``: any smooth function of several means
  by the delta method;
* ``holm``: Holm's step-down adjustment of a family of p-values; ``tied_with_best``: the tied group of a
  column, Holm over every pair of its rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy import stats as sps

from .sample import (  # noqa: F401 - re-exported: the tables and tests know them as stats.*
    MIN_PATIENTS,
    MIN_SEEDS,
    PATIENT,
    SAMPLING_UNITS,
    TRAJECTORY,
    Key,
    Sample,
    collapse,
    common_keys,
    refusal,
)

ALPHA = 0.05
LEVEL = 0.95
LINEAR, POSITIVE, PERCENT = "linear", "positive", "percent"
ZERO_SHIFT = 0.3  # errors with exact zeros: the shift c of log(error + c), a share of the cell mean (bench_calibration)


# ---------------------------------------------------------------- array core (batched; the benchmark calls it)

@dataclass(frozen=True)
class Inference:
    """A linear combination of cell means: value, standard error and Satterthwaite df (arrays or floats)."""

    value: np.ndarray
    se: np.ndarray
    df: np.ndarray

    def interval(self, level: float = LEVEL) -> tuple[np.ndarray, np.ndarray]:
        """The plain (linear, symmetric) t interval."""
        half = sps.t.ppf(0.5 + level / 2.0, self.df) * self.se
        return self.value - half, self.value + half

    def logit_interval(self, level: float = LEVEL, top: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
        """The t interval of a figure in [0, top] (a percentage) on the logit scale (delta method): inside the
        bounds, asymmetric near them; a value on a bound (nothing varies) is its own interval."""
        q = sps.t.ppf(0.5 + level / 2.0, self.df)
        m = np.asarray(self.value, dtype=np.float64)
        p = np.clip(m / top, 0.0, 1.0)
        inner = (p > 0) & (p < 1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            eta = np.log(p / (1.0 - p))
            half = q * self.se / (top * p * (1.0 - p))
            lo = np.where(inner, top / (1.0 + np.exp(-(eta - half))), m)
            hi = np.where(inner, top / (1.0 + np.exp(-(eta + half))), m)
        return lo, hi

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

    Satterthwaite's df is liberal when a few-df part happens to come out small (the df then jumps to the other
    parts', exactly when the interval is too short); computing the df from the median-unbiased value (x 1.44 at
    2 df) removes that (bench_calibration: coverage 0.931 -> 0.941 at 3 seeds, seed-dominated).
    """
    with np.errstate(invalid="ignore"):
        return np.where(np.isinf(df), v, v * df / sps.chi2.ppf(0.5, df))  # infinite df (nothing varies): v itself


@dataclass(frozen=True)
class _Parts:
    """The variance parts of one cell ``errors (..., R, U)`` (normalised weights ``w``)."""

    seed: np.ndarray | None  # sigma_seed^2 / R (noise share removed, >= 0); None with one replicate
    seed_df: np.ndarray | None
    noise: np.ndarray | None  # MS of the seed x unit residual (sigma_noise^2); None with one replicate
    unit: np.ndarray | None  # variance of the weighted mean of the per-unit means; None with one unit
    n_eff: float  # 1 / sum(w^2): the units' effective number


def _parts(errors: np.ndarray, w: np.ndarray, coef=1.0) -> _Parts:
    r, u = errors.shape[-2:]
    n_eff = 1.0 / float(np.sum(w * w))
    unit = None
    if u > 1:
        per_unit = coef * errors.mean(-2) if np.ndim(coef) == 0 else coef[..., None] * errors.mean(-2)
        centred = per_unit - (per_unit @ w)[..., None]
        unit = u / (u - 1) * (centred ** 2 @ (w * w))
    if r < 2:
        return _Parts(None, None, None, unit, n_eff)
    seed_means = errors @ w  # (..., R)
    v_seed = coef ** 2 * seed_means.var(-1, ddof=1) / r
    sw2 = 1.0 / n_eff
    resid = errors - seed_means[..., :, None] - errors.mean(-2)[..., None, :] + (seed_means.mean(-1))[..., None, None]
    ms_noise = (resid ** 2 @ w).sum(-1) / ((r - 1) * max(1.0 - sw2, 1e-12))
    v_noise = coef ** 2 * sw2 * ms_noise / r  # the noise share, also in the unit part
    seed = np.maximum(v_seed - v_noise, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = v_seed ** 2 / (r - 1) + v_noise ** 2 / ((r - 1) * max(u - 1, 1))
        df = np.maximum(np.where(denom > 0, seed ** 2 / denom, np.inf), 1.0)
    return _Parts(seed, df, ms_noise, unit, n_eff)


def _weighted_df(w: np.ndarray) -> float:
    """The df of a weighted variance over units with normalised weights ``w``: (sum w^2)^2 / sum w^4 - 1, U - 1
    for equal weights. With unequal pair counts it is below n_eff - 1 (6.1 vs 8.6 for the pair counts 10-59 of
    12 trajectories), which the lognormal-trajectory regime needs (coverage 0.915 -> 0.936)."""
    return max(float(np.sum(w * w) ** 2 / np.sum(w ** 4)) - 1.0, 1.0)


def combine(errors: Sequence[np.ndarray], weights: np.ndarray, coefs: Sequence) -> Inference:
    """Inference on ``sum_i coefs[i] * mean_i``, the cells ``errors[i] (..., R_i, U)`` on the same U units.

    Leading dimensions are a batch (independent experiments); ``coefs`` may be arrays of that batch shape.
    """
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    coefs = [np.asarray(c, dtype=np.float64) for c in coefs]
    value = sum(c * (e @ w).mean(-1) for c, e in zip(coefs, errors))
    terms: list[tuple[np.ndarray, float]] = []
    for_df: list[np.ndarray] = []
    if len(w) > 1:  # one unit part for the combination: shared difficulty cancels (the pairing)
        per_unit = sum(c[..., None] * e.mean(-2) for c, e in zip(coefs, errors))
        centred = per_unit - (per_unit @ w)[..., None]
        v_unit = len(w) / (len(w) - 1) * (centred ** 2 @ (w * w))
        unit_df = _weighted_df(w)
        terms.append((v_unit, unit_df))
        for_df.append(v_unit)
    for c, e in zip(coefs, errors):
        parts = _parts(e, w, c)
        if parts.seed is not None:
            terms.append((parts.seed, parts.seed_df))  # type: ignore[arg-type]
            for_df.append(_median_unbiased(parts.seed, parts.seed_df))
    if not terms:  # one replicate of one unit: no variation to measure
        nan = np.full_like(np.asarray(value, dtype=np.float64), np.nan)
        return Inference(np.asarray(value), nan, nan)
    total, df = _satterthwaite(terms, for_df)
    return Inference(np.asarray(value), np.sqrt(np.maximum(total, 0.0)), df)


def positive_interval(errors: np.ndarray, weights: np.ndarray, level: float = LEVEL
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The interval of the mean of one cell of positive, possibly right-skewed errors ``(..., R, U)``.

    On the log scale the variance parts of ``log error`` are estimated as in ``combine``, and the interval is
    Cox's for a lognormal mean, log(mean) = E[log error] + sigma^2 / 2 with sigma^2 the sum of the seed, unit
    and noise parts: ``exp(m + s/2 +- t sqrt(se^2 + var(s) / 4))``. It stays above 0, widens upwards where
    the errors are skewed (a bad seed, a hard trajectory) and equals the linear t interval to first order where
    they vary little relative to their mean; the seed and unit parts enter the centre, var(s) and the df of the
    t quantile at their median-unbiased values (bench_calibration: a lognormal patient factor, sigma 1, over 3
    patients, is covered 0.93 instead of 0.92). The arithmetic mean itself is always inside. Errors that are not
    all > 0: ``zeros_interval``.
    """
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mean = (errors @ w).mean(-1)
    if not np.all(errors > 0):
        return zeros_interval(errors, w, level)
    y = np.log(errors)
    inf = combine([y], w, [1.0])
    parts = _parts(y, w)
    r, u = y.shape[-2:]
    zero = np.zeros_like(inf.value, dtype=np.float64)
    seed = zero if parts.seed is None else r * _median_unbiased(parts.seed, parts.seed_df)
    unit_df = _weighted_df(w)
    unit_mu = unit_df / sps.chi2.ppf(0.5, unit_df)  # the unit part at its median-unbiased value too (x 1.44 at 2 df)
    unit = zero if parts.unit is None else parts.n_eff * parts.unit * unit_mu  # sigma_unit^2 + sigma_noise^2 / R
    noise = zero if parts.noise is None else parts.noise * (1.0 - 1.0 / r)
    var_s = 2.0 * unit ** 2 / unit_df
    if parts.seed is not None:
        var_s = var_s + 2.0 * seed ** 2 / parts.seed_df + 2.0 * noise ** 2 / ((r - 1) * max(u - 1, 1))
    v_unit = zero if parts.unit is None else parts.unit * unit_mu
    v_seed = zero if parts.seed is None else _median_unbiased(parts.seed, parts.seed_df)
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = v_unit ** 2 / unit_df + (0.0 if parts.seed is None else v_seed ** 2 / parts.seed_df)
        df = np.where(denom > 0, (v_unit + v_seed) ** 2 / denom, inf.df)
    centre = inf.value + (seed + unit + noise) / 2.0
    with np.errstate(invalid="ignore"):
        half = sps.t.ppf(0.5 + level / 2.0, df) * np.sqrt(inf.se ** 2 + var_s / 4.0)
        lo, hi = np.exp(centre - half), np.exp(centre + half)
    return np.minimum(lo, mean), np.maximum(hi, mean)


def zeros_interval(errors: np.ndarray, weights: np.ndarray, level: float = LEVEL
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The interval of a mean of errors >= 0 with exact zeros (an ATE or drift of 0 on some trajectories): Cox's
    interval of ``errors + c`` shifted back by ``c``, with ``c`` = ``ZERO_SHIFT`` x the cell mean, so the skew is
    still handled on the log scale (bench_calibration, 20 % zero trajectories: 0.96 where the linear interval
    covered 0.88); the lower bound is clipped at 0. Every value 0: no interval (NaN)."""
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mean = (errors @ w).mean(-1)
    c = ZERO_SHIFT * np.asarray(mean, dtype=np.float64)[..., None, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        shifted = np.where(c > 0, errors + c, np.nan)
        lo, hi = positive_interval(shifted, w, level) if np.all(np.isfinite(shifted)) else (
            np.full_like(mean, np.nan), np.full_like(mean, np.nan))
    c = c[..., 0, 0]
    return np.where(c > 0, np.maximum(lo - c, 0.0), np.nan), np.where(c > 0, hi - c, np.nan)


def zero_percent_bound(units: int, level: float = LEVEL, top: float = 100.0) -> float:
    """An honest upper bound for a percentage that is 0 on every one of ``units`` independent units (trajectories,
    or patients): the mean can exceed 0 only if some units can, and with all ``units`` at 0 the share of units
    that can is below 1 - ((1 - level) / 2) ** (1 / units) (Clopper-Pearson); the mean is at most that share x
    ``top`` (the rule of three, conservative: a unit's value is at most ``top``). 12 units: 26.5 %."""
    return top * (1.0 - ((1.0 - level) / 2.0) ** (1.0 / units))


# ---------------------------------------------------------------- on samples (what the tables call)

def _aligned(samples: Sequence[Sample]) -> list[Sample]:
    keys = common_keys(samples)
    if not keys:
        raise ValueError("the samples share no test trajectory")
    if len({s.unit for s in samples}) > 1:
        raise ValueError("the samples state different estimands (units)")
    return [s.restricted(keys) for s in samples]


def linear(samples: Sequence[Sample], coefs: Sequence[float]) -> Inference:
    """Inference on ``sum_i coefs[i] * mean_i`` over the samples' shared trajectories (grouped into patients
    for a new-patient estimand)."""
    aligned = _aligned(samples)
    units = [s.units() for s in aligned]
    return combine([e for e, _ in units], units[0][1], coefs)


def interval(sample: Sample, level: float = LEVEL, scale: str = LINEAR) -> tuple[float, float]:
    """The interval of the sample's mean on ``scale``; NaN bounds when it is refused (``refusal``) or nothing
    varies that could be measured (one replicate, one unit)."""
    if refusal(sample):
        return math.nan, math.nan
    errors, weights = sample.units()
    if scale == PERCENT and (np.all(errors == 0) or np.all(errors == 100.0)):  # nothing varies: an honest bound
        bound = zero_percent_bound(errors.shape[-1], level)
        return (0.0, bound) if np.all(errors == 0) else (100.0 - bound, 100.0)
    if not np.any(errors):  # every error 0 (positive or linear): no width can be justified
        return math.nan, math.nan
    if scale == POSITIVE:
        lo, hi = positive_interval(errors, weights, level)
    elif scale == PERCENT:
        lo, hi = combine([errors], weights, [1.0]).logit_interval(level)
    elif scale == LINEAR:
        lo, hi = combine([errors], weights, [1.0]).interval(level)
    else:
        raise ValueError(f"scale {scale!r} is not one of {LINEAR}, {POSITIVE}, {PERCENT}")
    return float(lo), float(hi)


def paired_p(a: Sample, b: Sample) -> float:
    """Two-sided test of equal means of ``a`` and ``b`` on their shared units (seeds independent)."""
    return float(linear([a, b], [1.0, -1.0]).p)


def holm_array(p: np.ndarray) -> np.ndarray:
    """Holm step-down adjusted p-values of the families along the last axis (batched; NaN-free input)."""
    p = np.asarray(p, dtype=np.float64)
    m = p.shape[-1]
    if m == 0:
        return p.copy()
    order = np.argsort(p, axis=-1, kind="stable")
    ranked = np.take_along_axis(p, order, -1) * (m - np.arange(m))
    adjusted = np.minimum(1.0, np.maximum.accumulate(ranked, axis=-1))
    out = np.empty_like(adjusted)
    np.put_along_axis(out, order, adjusted, -1)
    return out


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm step-down adjusted p-values, in the input order."""
    return holm_array(np.asarray(pvalues, dtype=np.float64)).tolist()


def tied_with_best(means: np.ndarray, pair_p: np.ndarray, alpha: float = ALPHA, higher: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tied group of a column (batched over leading axes): ``means (..., k)`` of the rows, ``pair_p (..., k,
    k)`` the paired p of every two rows (symmetric). The best is the lowest mean (highest if ``higher``); the
    family is **every pair of rows**, Holm-adjusted, because which row is compared with the others is chosen by
    the data (comparing only the best with the others, Holm over k - 1, left a truly equal row out 0.07 of the
    time at 5 seeds; bench_calibration ``tied group``). Returns (best index, adjusted p of best vs each row
    (1 for the best itself), tied mask)."""
    means = np.asarray(means, dtype=np.float64)
    k = means.shape[-1]
    best = np.argmax(means, -1) if higher else np.argmin(means, -1)
    iu, ju = np.triu_indices(k, 1)
    adjusted = holm_array(np.asarray(pair_p)[..., iu, ju])
    full = np.ones(means.shape[:-1] + (k, k))
    full[..., iu, ju] = adjusted
    full[..., ju, iu] = adjusted
    vs_best = np.take_along_axis(full, best[..., None, None], -2)[..., 0, :]
    vs_best = np.where(np.arange(k) == best[..., None], 1.0, vs_best)
    return best, vs_best, vs_best >= alpha


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
    """1 - model error / reference error (0: no better than the reference; 1: perfect), its interval by the
    delta method on log(model / reference) so that it never exceeds 1; p of 'skill is 0'."""
    lr = derived([model, reference], lambda m, r: math.log(m / r) if m > 0 and r > 0 else math.nan, level)
    return Derived(1.0 - math.exp(lr.value), 1.0 - math.exp(lr.hi), 1.0 - math.exp(lr.lo), lr.p, lr.df)
