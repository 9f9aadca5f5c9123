"""Pooling per-run statistics into one table cell (several folds and/or seeds).

Each run logs, per metric, the mean and population std (ddof=0) over its own
test pairs or trajectories, and how many there were (``test.n_pairs``,
``test.n_trajectories``). Pooling treats the union of all those values as one
sample, exactly: with run i contributing n_i values of mean mu_i and std s_i,

    N = sum n_i,  mu = sum n_i mu_i / N,  var = sum n_i (s_i^2 + mu_i^2) / N - mu^2,

i.e. the mean and population std the report would get from the raw per-pair
(per-trajectory) errors of all held-out patients together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from ..metrics import Stat
from .collect import RunRecord

EVALS = ("accumulated", "pair")
PREFIX = {"accumulated": "acc", "pair": "pair"}
COUNT = {"accumulated": "test.n_trajectories", "pair": "test.n_pairs"}
NOUN = {"accumulated": "test trajectories", "pair": "test image pairs"}


def pooled(stats: Sequence[Stat]) -> Stat:
    """Mean and population std of the union of the samples behind ``stats`` (see the module doc)."""
    if not stats:
        raise ValueError("nothing to pool")
    if len(stats) == 1:
        return stats[0]
    total = sum(s.n for s in stats)
    if total <= 0:
        raise ValueError("pooling needs the sample size of every run")
    mean = sum(s.n * s.mean for s in stats) / total
    second = sum(s.n * (s.std ** 2 + s.mean ** 2) for s in stats) / total
    return Stat(mean, math.sqrt(max(second - mean * mean, 0.0)), total)


@dataclass(frozen=True)
class CellValue:
    """A pooled table cell, or why there is none (``stat`` None, ``problem`` says why)."""

    stat: Stat | None
    runs: tuple[str, ...] = ()
    problem: str = ""


def run_stat(run: RunRecord, metric: str, evaluation: str) -> Stat | None:
    """One run's ``<prefix>.<metric>`` mean/std and its sample size (0 when not logged); None if absent."""
    key = f"{PREFIX[evaluation]}.{metric}"
    mean, std = run.metrics.get(f"{key}.mean"), run.metrics.get(f"{key}.std")
    if mean is None or std is None or math.isnan(mean):
        return None
    n = run.metrics.get(COUNT[evaluation])
    return Stat(float(mean), float(std), int(n) if n is not None and not math.isnan(n) else 0)


def cell_value(runs: Sequence[RunRecord], metric: str, evaluation: str) -> CellValue:
    """Pool one metric over ``runs``; a run lacking the metric (or, when pooling, its count) empties the cell."""
    ids = tuple(r.run_id for r in runs)
    stats = []
    for r in runs:
        s = run_stat(r, metric, evaluation)
        if s is None:
            return CellValue(None, ids, f"run {r.run_id} has no metric {PREFIX[evaluation]}.{metric}.mean/.std")
        if len(runs) > 1 and s.n <= 0:
            return CellValue(None, ids, f"run {r.run_id} has no {COUNT[evaluation]} to weight the pooled mean")
        stats.append(s)
    return CellValue(pooled(stats), ids)
