"""A table cell's data: per-trajectory errors of each replicate, and the estimand they are read for.

``Sample.unit`` states the estimand (stats.py): ``trajectory`` (these
patients: seeds and trajectories vary) or ``patient`` (a new patient: the
trajectories are averaged into their patients first, so patients are a level).
``refusal`` says when a sample supports no interval and no test. With fewer than
``MIN_SEEDS`` replicates how seeds differ cannot be measured: the estimand is then
the trained models themselves (``seeds_fixed``: each trajectory's error averaged
over the replicates, the interval covering new test units only, not new seeds).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

Key = tuple[str, str, str]  # (patient, lobe, trajectory)
TRAJECTORY, PATIENT = "trajectory", "patient"  # the sampling unit: "these patients" / "a new patient"
SAMPLING_UNITS = (TRAJECTORY, PATIENT)  # what an interval generalises over (not units of measure)
MIN_SEEDS = 3  # fewer seeds (1 or 2): the estimand is the trained models, seeds fixed (the units only, said so)
MIN_PATIENTS = 3  # a new-patient interval needs 3 patients (2 df)


@dataclass(frozen=True)
class Sample:
    """Per-trajectory errors of one cell: ``errors[r, t]`` for replicate r and trajectory ``keys[t]``."""

    keys: tuple[Key, ...]
    weights: np.ndarray  # (T,) n_pairs (per-pair metrics) or ones (accumulated)
    errors: np.ndarray  # (R, T)
    pairs: int = 0  # test pairs behind the T trajectories
    unit: str = TRAJECTORY  # what the interval generalises over (module doc)

    def __post_init__(self) -> None:
        if self.errors.ndim != 2 or self.errors.shape[1] != len(self.keys) or len(self.weights) != len(self.keys):
            raise ValueError(f"errors {self.errors.shape} do not match {len(self.keys)} keys / weights")
        if self.unit not in SAMPLING_UNITS:
            raise ValueError(f"unit {self.unit!r} is not one of {', '.join(SAMPLING_UNITS)}")

    @property
    def replicates(self) -> int:
        return int(self.errors.shape[0])

    @property
    def seeds_fixed(self) -> bool:
        """Too few replicates to measure how seeds differ (< MIN_SEEDS): the sample is read for its trained
        models, not for new seeds."""
        return self.replicates < MIN_SEEDS

    @property
    def trajectories(self) -> int:
        return len(self.keys)

    @property
    def patients(self) -> int:
        return len({k[0] for k in self.keys})

    @property
    def mean(self) -> float:
        return float(np.mean(self.errors @ self.weights / self.weights.sum()))

    def restricted(self, keys: Sequence[Key]) -> "Sample":
        """The same sample on ``keys`` (a subset of its own), in that order."""
        pos = {k: i for i, k in enumerate(self.keys)}
        idx = np.array([pos[k] for k in keys], dtype=int)
        return replace(self, keys=tuple(keys), weights=self.weights[idx], errors=self.errors[:, idx])

    def as_unit(self, unit: str) -> "Sample":
        return replace(self, unit=unit)

    def units(self) -> tuple[np.ndarray, np.ndarray]:
        """``(errors (R, U), weights (U,))`` over the sampling units: the trajectories, or the patients (each
        the weighted mean of its trajectories, its weight their summed weight). With its seeds fixed
        (``seeds_fixed``) the replicates are averaged first: one row, the trained models' mean error per unit."""
        errors = self.errors.mean(0, keepdims=True) if self.seeds_fixed else self.errors
        if self.unit == TRAJECTORY:
            return errors, self.weights
        names = sorted({k[0] for k in self.keys})
        groups = np.array([names.index(k[0]) for k in self.keys])
        return collapse(errors, self.weights, groups, len(names))


def collapse(errors: np.ndarray, weights: np.ndarray, groups: np.ndarray, n_groups: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """Weighted means of ``errors (..., R, T)`` over the trajectories of each group (``groups[t]`` in
    ``range(n_groups)``): ``(errors (..., R, G), weights (G,))``. The weighted grand mean is unchanged."""
    member = np.zeros((len(groups), n_groups))
    member[np.arange(len(groups)), groups] = 1.0
    w = np.asarray(weights, dtype=np.float64)
    total = w @ member
    return (errors * w) @ member / total, total


def refusal(sample: Sample) -> str:
    """Why the sample gets no interval and no test ("" when it does): too few patients for a new-patient
    estimand. (Too few seeds is not a refusal: the estimand becomes the trained models, ``seeds_fixed``.)"""
    if sample.unit == PATIENT and sample.patients < MIN_PATIENTS:
        return f"{sample.patients} patient{'s' if sample.patients != 1 else ''}"
    return ""


def common_keys(samples: Sequence[Sample]) -> list[Key]:
    """The trajectories every sample has, sorted (what a comparison is computed on)."""
    keys = set(samples[0].keys)
    for s in samples[1:]:
        keys &= set(s.keys)
    return sorted(keys)
