"""The statistics behind every table cell: a two-level bootstrap over seeds and test trajectories.

A cell's data is a :class:`Sample`: for each replicate (a seed; for
cross-subject the fold runs of one seed together) the per-trajectory error of
every shared test trajectory, and each trajectory's weight (its number of
pairs for per-pair metrics, 1 for accumulated ones). Its value is the mean over
replicates of the weighted mean over trajectories, i.e. the mean of the
run-level metric the runs logged.

Resampling (vectorised, ``RESAMPLES`` draws, a fixed RNG seed so a report is
reproducible): the replicates of each sample are drawn with replacement and,
jointly, the test trajectories are drawn with replacement, the same draw for
every sample being compared (the trajectory keys are aligned first), so

* ``interval``: 95 % percentile interval of one sample's mean;
* ``paired_p``: two rows on the same trajectories, trajectories drawn jointly,
  replicates independently per row; two-sided p = 2 min(P*(d <= 0), P*(d >= 0))
  of the bootstrap distribution of the difference d of the means (with the +1
  correction, so p >= 2 / (B + 1));
* ``skill``: 1 - error / reference error, both on the same draw;
* ``holm``: Holm's step-down adjustment of a family of p-values.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

RESAMPLES = 2000
SEED = 20240614
ALPHA = 0.05
LEVEL = 0.95
Key = tuple[str, str, str]  # (patient, lobe, trajectory)


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
    """The trajectories every sample has, sorted (what a joint resampling draws from)."""
    keys = set(samples[0].keys)
    for s in samples[1:]:
        keys &= set(s.keys)
    return sorted(keys)


def _counts(rng: np.random.Generator, n: int, draws: int) -> np.ndarray:
    """``(draws, n)``: how often each of n items is drawn in each of ``draws`` resamples of size n."""
    idx = rng.integers(0, n, size=(draws, n)) + (np.arange(draws) * n)[:, None]
    return np.bincount(idx.ravel(), minlength=draws * n).reshape(draws, n).astype(np.float64)


def joint_means(samples: Sequence[Sample], resamples: int = RESAMPLES, seed: int = SEED
                ) -> tuple[np.ndarray, np.ndarray]:
    """Means of each sample on their common trajectories: the point values ``(k,)`` and ``(B, k)`` resampled.

    One trajectory draw per resample shared by all samples; replicates drawn independently per sample.
    """
    keys = common_keys(samples)
    if not keys:
        raise ValueError("the samples share no test trajectory")
    aligned = [s.restricted(keys) for s in samples]
    rng = np.random.default_rng(seed)
    traj = _counts(rng, len(keys), resamples)  # (B, T)
    point, boot = [], []
    for s in aligned:
        cw = traj * s.weights  # (B, T)
        per_rep = (cw @ s.errors.T) / cw.sum(1, keepdims=True)  # (B, R)
        reps = _counts(rng, s.replicates, resamples)  # (B, R)
        boot.append((reps * per_rep).sum(1) / s.replicates)
        point.append(s.mean)
    return np.array(point), np.stack(boot, 1)


def percentile_interval(values: np.ndarray, level: float = LEVEL) -> tuple[float, float]:
    tail = (1.0 - level) / 2.0 * 100.0
    lo, hi = np.percentile(values, [tail, 100.0 - tail])
    return float(lo), float(hi)


def interval(sample: Sample, resamples: int = RESAMPLES, seed: int = SEED) -> tuple[float, float]:
    """95 % two-level percentile bootstrap interval of the sample's mean."""
    _, boot = joint_means([sample], resamples, seed)
    return percentile_interval(boot[:, 0])


def two_sided_p(diff: np.ndarray) -> float:
    """Two-sided bootstrap p of 'difference = 0' from the resampled differences (+1 corrected)."""
    b = len(diff)
    below = (np.count_nonzero(diff <= 0) + 1) / (b + 1)
    above = (np.count_nonzero(diff >= 0) + 1) / (b + 1)
    return float(min(1.0, 2.0 * min(below, above)))


def paired_p(a: Sample, b: Sample, resamples: int = RESAMPLES, seed: int = SEED) -> float:
    """Paired two-level bootstrap test of equal means of ``a`` and ``b`` on their shared trajectories."""
    _, boot = joint_means([a, b], resamples, seed)
    return two_sided_p(boot[:, 0] - boot[:, 1])


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
    """A statistic of several samples with its interval (e.g. a skill)."""

    value: float
    lo: float
    hi: float
    boot: np.ndarray


def derived(samples: Sequence[Sample], fn: Callable[..., np.ndarray], resamples: int = RESAMPLES,
            seed: int = SEED) -> Derived:
    """``fn(*means)`` at the point values and on every joint resample, with its percentile interval."""
    point, boot = joint_means(samples, resamples, seed)
    values = fn(*boot.T)
    lo, hi = percentile_interval(values)
    return Derived(float(fn(*point)), lo, hi, values)


def skill(model: Sample, reference: Sample, resamples: int = RESAMPLES, seed: int = SEED) -> Derived:
    """1 - model error / reference error (0: no better than the reference; 1: perfect)."""
    return derived([model, reference], lambda m, r: 1.0 - m / r, resamples, seed)
