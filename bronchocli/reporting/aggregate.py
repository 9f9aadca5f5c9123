"""From runs to the samples behind table cells: replicates, per-trajectory errors, references.

Every run logs ``trajectory_errors.csv``: one row per test trajectory
(patient, lobe, trajectory, n_pairs) with ``<source>.<scope>.<metric>`` for
source in model / zero_motion / train_mean and scope in pair (the
trajectory's mean per-pair error) / acc (its endpoint error after chaining) /
traj (its camera-tracking metrics: CTF, ATE, RPE, drift; odometry.py).

* A **replicate** is one seed: one run (personalized), or the fold runs of one
  seed together (cross-subject: their test trajectories are those of the
  different held-out patients, so their union is the replicate's test set).
* A **model sample** holds, per replicate, the error of each test trajectory
  the replicates share; per-pair metrics weight each trajectory by its pairs,
  so the sample mean is exactly the logged ``pair.<m>.mean`` (mean over all
  pairs) averaged over seeds, and ``acc.<m>.mean`` likewise.
* A **reference sample** (zero motion, training mean) averages each
  trajectory's reference error over every run that has it (the references do
  not depend on the model or seed, only on the split), as one replicate.

A run without ``trajectory_errors.csv`` (made before it existed) falls back to
its logged means (``logged_mean``): a value without interval or test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from .. import runkeys
from .collect import RunRecord, seed_key
from .stats import TRAJECTORY, Key, Sample

EVALS = ("accumulated", "pair")  # what --eval chooses; "trajectory" is the tracking table's own scope
SCOPE = {"accumulated": "acc", "pair": "pair", "trajectory": "traj"}
COUNT = {evaluation: runkeys.count(scope) for evaluation, scope in SCOPE.items()}  # what a scope's means are over
KEY = ["patient", "lobe", "trajectory"]
REFERENCES = dict(zip(runkeys.REFERENCES, ("Zero motion", "Training mean")))
ERRORS_CSV = "trajectory_errors.csv"

Frames = Mapping[str, "RunErrors | None"]  # run id -> its trajectory_errors.csv (None: absent)


@dataclass(frozen=True)
class RunErrors:
    """One run's (or one replicate's) trajectory_errors.csv as arrays: rows in ``keys`` order."""

    keys: tuple[Key, ...]
    n_pairs: np.ndarray
    columns: Mapping[str, np.ndarray]

    @classmethod
    def from_frame(cls, df: pd.DataFrame) -> "RunErrors":
        df = df.astype({k: str for k in KEY}).drop_duplicates(subset=KEY)
        keys = tuple(zip(*(df[k].tolist() for k in KEY)))
        n = df["n_pairs"].to_numpy(dtype=np.float64) if "n_pairs" in df else np.ones(len(df))
        cols = {c: df[c].to_numpy(dtype=np.float64) for c in df.columns if c not in KEY and c != "n_pairs"}
        return cls(keys, n, cols)  # type: ignore[arg-type]

    @classmethod
    def concat(cls, parts: Sequence["RunErrors"]) -> "RunErrors":
        if len(parts) == 1:
            return parts[0]
        seen: set[Key] = set()
        keep = [[k not in seen and not seen.add(k) for k in p.keys] for p in parts]  # first occurrence wins
        keys = tuple(k for p, m in zip(parts, keep) for k, ok in zip(p.keys, m) if ok)
        names = set.intersection(*(set(p.columns) for p in parts))
        n = np.concatenate([p.n_pairs[np.array(m, bool)] for p, m in zip(parts, keep)])
        cols = {c: np.concatenate([p.columns[c][np.array(m, bool)] for p, m in zip(parts, keep)]) for c in names}
        return cls(keys, n, cols)

    def take(self, keys: Sequence[Key]) -> np.ndarray:
        pos = {k: i for i, k in enumerate(self.keys)}
        return np.array([pos[k] for k in keys], dtype=int)


def read_errors(path) -> RunErrors:
    """A trajectory_errors.csv, keys as strings."""
    return RunErrors.from_frame(pd.read_csv(path, dtype={k: str for k in KEY}))


def nonfinite_rows(frames: Frames) -> dict[str, int]:
    """Run id -> how many rows of its trajectory_errors.csv hold a NaN/inf error (they leave the intervals)."""
    out = {}
    for run_id, errors in frames.items():
        if errors is None or not errors.columns:
            continue
        bad = ~np.isfinite(np.stack(list(errors.columns.values()))).all(0)
        if bad.any():
            out[run_id] = int(bad.sum())
    return out


def column(source: str, evaluation: str, metric: str) -> str:
    return runkeys.column(metric, SCOPE[evaluation], source)


def replicates(runs: Sequence[RunRecord]) -> list[list[RunRecord]]:
    """The runs grouped by seed (sorted): the replicates of a row."""
    groups: dict[str, list[RunRecord]] = {}
    for r in runs:
        groups.setdefault(r.tag("seed"), []).append(r)
    return [groups[s] for s in sorted(groups, key=seed_key)]


def _replicate(rep: Sequence[RunRecord], frames: Frames) -> RunErrors | None:
    parts = [frames.get(r.run_id) for r in rep]
    if any(p is None for p in parts):
        return None
    return RunErrors.concat(parts)  # type: ignore[arg-type]


def _sample(tables: Sequence[RunErrors], col: str, evaluation: str, unit: str = TRAJECTORY) -> Sample | None:
    if not tables or any(col not in t.columns for t in tables):
        return None
    common = set(tables[0].keys)
    for t in tables[1:]:
        common &= set(t.keys)
    keys = sorted(common)
    if not keys:
        return None
    errors = np.stack([t.columns[col][t.take(keys)] for t in tables])
    pairs = tables[0].n_pairs[tables[0].take(keys)]
    ok = np.isfinite(errors).all(0)
    if not ok.any():
        return None
    weights = pairs if evaluation == "pair" else np.ones(len(keys))
    kept = tuple(k for k, good in zip(keys, ok) if good)
    return Sample(kept, weights[ok], errors[:, ok], int(pairs[ok].sum()), unit)


def model_sample(reps: Sequence[Sequence[RunRecord]], frames: Frames, evaluation: str, metric: str,
                 source: str = "model", unit: str = TRAJECTORY) -> Sample | None:
    """Per replicate, the error of every shared test trajectory (None when a run lacks its errors table);
    ``unit``: the estimand its intervals state (stats.TRAJECTORY: these patients, stats.PATIENT: a new one)."""
    tables = [_replicate(rep, frames) for rep in reps]
    if not tables or any(t is None for t in tables):
        return None
    return _sample(tables, column(source, evaluation, metric), evaluation, unit)  # type: ignore[arg-type]


def reference_sample(runs: Sequence[RunRecord], frames: Frames, source: str, evaluation: str,
                     metric: str, unit: str = TRAJECTORY) -> Sample | None:
    """One replicate: each trajectory's ``source`` error averaged over every run (with an errors table) that has it."""
    col = column(source, evaluation, metric)
    parts = [t for r in runs if (t := frames.get(r.run_id)) is not None and col in t.columns]
    if not parts:
        return None
    keys = sorted({k for p in parts for k in p.keys})
    pos = {k: i for i, k in enumerate(keys)}
    total, count, pairs = np.zeros(len(keys)), np.zeros(len(keys)), np.zeros(len(keys))
    for p in parts:
        idx = np.array([pos[k] for k in p.keys], dtype=int)
        np.add.at(total, idx, p.columns[col])
        np.add.at(count, idx, 1.0)
        pairs[idx] = p.n_pairs
    mean = RunErrors(tuple(keys), pairs, {col: total / count})
    return _sample([mean], col, evaluation, unit)


def _run_mean(run: RunRecord, name: str) -> float | None:
    v = run.metrics.get(name)
    return None if v is None or math.isnan(v) else float(v)


def logged_mean(reps: Sequence[Sequence[RunRecord]], evaluation: str, metric: str,
                source: str = "model") -> float | None:
    """Fallback without errors tables: per replicate the test-count-weighted mean of its runs' logged means
    (the mean over the union of their test pairs/trajectories), averaged over replicates."""
    name = runkeys.metric(metric, SCOPE[evaluation], ref=source)
    values = []
    for rep in reps:
        means = [_run_mean(r, name) for r in rep]
        if any(m is None for m in means):
            return None
        counts = [_run_mean(r, COUNT[evaluation]) or 0.0 for r in rep]
        if len(rep) > 1 and not all(counts):
            return None
        total = sum(counts)
        values.append(sum(c * m for c, m in zip(counts, means)) / total if len(rep) > 1 else means[0])  # type: ignore
    return float(np.mean(values)) if values else None
