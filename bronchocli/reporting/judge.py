"""Metric rows of a table with their intervals, reference rows, significance marks and skill.

``metric_rows`` turns table lines (a row label and its runs) into rows whose
error cells are ``mean [95 % interval]`` over the row's replicates (seeds),
adds the two image-blind reference rows, and decides the marks of every error
column (``judge_column``):

1. the row with the lowest mean is the candidate best;
2. every two rows of the column are compared by the paired t test
   (``stats.paired_p``: variance components over seeds and the shared test
   trajectories, Satterthwaite df), and the p-values are Holm-adjusted over
   all those pairs (the best is chosen by the data, so the family is every
   pair: ``stats.tied_with_best``);
3. the rows whose adjusted p is >= alpha are tied with it. Alone, it is the
   ``best``; otherwise every row of the tied group is marked ``tie`` and the
   caption says that no row is significantly best at that number of seeds.

A row whose sample ``stats.refusal`` refuses (2 seeds, or too few patients for
a new-patient estimand) shows its mean only and takes no part in the marks or
skill (estimand.py). Each row is compared with the better reference (the
lower mean; the higher for CTF) by one paired comparison on their shared test
units (``versus_reference``): skill = 1 - error / reference error with its
interval on the log-ratio scale (delta method, ``stats.skill``), for CTF the
difference. A row whose paired interval does not lie above 0 is marked
``noskill`` (†), and the skill figure colours a bar by the same verdict
(``beats_reference``): one rule, per cell, no multiplicity correction. Rows
without per-trajectory errors (logged means) fall back to their mean against
the reference's. A row whose predictions vary less than ``IGNORES_RATIO`` of
the ground truth's (``pred.std_ratio.pos``) is flagged ``ignores``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .. import runkeys
from . import stats
from .aggregate import REFERENCES, Frames, logged_mean, model_sample, reference_sample, replicates
from .collect import RunRecord
from .estimand import scale_of
from .table_model import Estimate, Row, Value

IGNORES_RATIO = 0.05
REFERENCE_GROUP = "Image-blind"


@dataclass
class Settings:
    alpha: float = stats.ALPHA
    level: float = stats.LEVEL


@dataclass
class Line:
    """A model row to build: its labels, its runs (complete replicates only) and leading non-metric values."""

    group: str
    label: str
    runs: list[RunRecord]
    extra: list[Value] = field(default_factory=list)
    model: str = ""  # the model's one name (registry.model_name); the label shows it, or it with the group


@dataclass
class Built:
    rows: list[Row]
    marks: list[list[set[str]]]
    skill: dict[str, dict[str, stats.Derived]]
    references: dict[str, list[stats.Sample | None]]  # source -> per metric
    fallback: list[str]  # rows shown from logged means (no trajectory_errors.csv)
    unsettled: list[str] = field(default_factory=list)  # metrics whose column has no significant best


def estimate(sample: stats.Sample | None, fallback: float | None, s: Settings,
             scale: str = stats.POSITIVE) -> Estimate | None:
    """The cell: the sample's mean with its interval on ``scale`` (none when refused or nothing varies), else
    the logged mean."""
    if sample is not None:
        lo, hi = stats.interval(sample, s.level, scale)
        return Estimate(sample.mean, lo, hi) if lo == lo else Estimate(sample.mean)  # NaN: no interval
    return None if fallback is None else Estimate(fallback)


def judged(sample: stats.Sample | None) -> stats.Sample | None:
    """The sample if it may be ranked and tested (not refused: stats.refusal), else None."""
    return None if sample is None or stats.refusal(sample) else sample


def ignores_input(runs: Sequence[RunRecord]) -> bool:
    ratios = [r.metrics.get(runkeys.spread("pos", relative=True)) for r in runs]
    ratios = [v for v in ratios if v is not None and not math.isnan(v)]
    return bool(ratios) and float(np.mean(ratios)) < IGNORES_RATIO


def _model_row(line: Line, frames: Frames, metrics: Sequence[str], evaluation: str, s: Settings, unit: str) -> Row:
    reps = replicates(line.runs)
    samples = [model_sample(reps, frames, evaluation, m, unit=unit) if reps else None for m in metrics]
    values: list[Value] = list(line.extra)
    for m, sample in zip(metrics, samples):
        fallback = logged_mean(reps, evaluation, m) if reps else None
        values.append(estimate(sample, fallback, s, scale_of(m)) if reps else None)
    first = next((x for x in samples if x is not None), None)
    info = {"samples": samples, "replicates": len(reps), "runs": line.runs,
            "refused": stats.refusal(first) if first is not None else "",
            "trajectories": first.trajectories if first else None, "pairs": first.pairs if first else None}
    flags = {"ignores"} if line.runs and ignores_input(line.runs) else set()
    return Row(line.group, line.label, values, [r.run_id for r in line.runs], flags=flags, info=info,
               model=line.model)


def _reference_rows(runs: Sequence[RunRecord], frames: Frames, metrics: Sequence[str], evaluation: str,
                    n_extra: int, grouped: bool, s: Settings, unit: str) -> tuple[list[Row], dict[str, list]]:
    rows, samples = [], {}
    reps = replicates(runs)
    for source, name in REFERENCES.items():
        per_metric = [reference_sample(runs, frames, source, evaluation, m, unit) for m in metrics]
        values: list[Value] = [""] * n_extra
        values += [estimate(x, logged_mean(reps, evaluation, m, source) if reps else None, s, scale_of(m))
                   for x, m in zip(per_metric, metrics)]
        rows.append(Row(REFERENCE_GROUP if grouped else "", name, values, kind="reference"))
        samples[source] = per_metric
    return rows, samples


def judge_column(samples: Sequence[stats.Sample | None], s: Settings, higher: bool = False
                 ) -> tuple[list[set[str]], dict[int, float]]:
    """Marks of one column (per row) and the adjusted p of each row against the best (the lowest mean; the
    highest where ``higher`` is better, e.g. CTF), Holm over every pair of the judged rows (stats.tied_with_best)."""
    out: list[set[str]] = [set() for _ in samples]
    samples = [judged(x) for x in samples]
    cand = [i for i, x in enumerate(samples) if x is not None]
    if len(cand) < 2:
        return out, {}
    k = len(cand)
    pair_p = np.ones((k, k))
    for a in range(k):
        for b in range(a + 1, k):
            pair_p[a, b] = pair_p[b, a] = stats.paired_p(samples[cand[a]], samples[cand[b]])  # type: ignore[arg-type]
    means = np.array([samples[i].mean for i in cand])  # type: ignore[union-attr]
    best, vs_best, tied = stats.tied_with_best(means, pair_p, s.alpha, higher)
    adjusted = {cand[j]: float(vs_best[j]) for j in range(k) if j != int(best)}
    group = [cand[j] for j in range(k) if tied[j]]
    for i in group:
        out[i].add("best" if len(group) == 1 else "tie")
    return out, adjusted


def better_reference(refs: dict[str, list], j: int, higher: bool = False) -> stats.Sample | None:
    """The better reference's sample of metric ``j`` (None when none may be judged: stats.refusal)."""
    found = [x[j] for x in refs.values() if judged(x[j]) is not None]
    sign = -1.0 if higher else 1.0
    return min(found, key=lambda x: sign * x.mean) if found else None


def _no_skill(v: Estimate, bar: float, higher: bool) -> bool:
    """Without paired data (a row shown from logged means): the row's value does not lie beyond the better
    reference's mean (below it; above it if higher)."""
    if higher:
        return (v.lo if v.has_interval else v.mean) <= bar  # type: ignore[operator]
    return (v.hi if v.has_interval else v.mean) >= bar  # type: ignore[operator]


def versus_reference(model: stats.Sample, reference: stats.Sample, s: Settings, higher: bool = False
                     ) -> stats.Derived:
    """The one paired comparison of a row with the better reference on their shared test units: for an error,
    the skill 1 - error / reference error (interval on the log-ratio scale); for a higher-is-better figure
    (CTF), the difference model - reference. Both are > 0 where the row is better. ValueError: no shared unit."""
    if higher:
        return stats.derived([model, reference], lambda m, r: m - r, s.level)
    return stats.skill(model, reference, s.level)


def beats_reference(d: stats.Derived) -> bool:
    """The verdict the † mark and the skill figure's colour share: the paired 95% interval lies above 0 (per
    cell, no multiplicity correction: each cell's claim is about that row alone)."""
    return d.lo > 0


def metric_rows(lines: Sequence[Line], frames: Frames, metrics: Sequence[str], evaluation: str, *,
                grouped: bool, settings: Settings | None = None, skill_metrics: Sequence[str] = (),
                higher: Sequence[str] = (), unit: str = stats.TRAJECTORY) -> Built:
    """Model rows, then the two reference rows; marks for the metric columns (after the ``extra`` ones).
    ``higher``: the metrics where higher is better (CTF); the others are errors (lower is better). ``unit``:
    the estimand (estimand.unit_of: these patients or a new patient)."""
    s = settings or Settings()
    n_extra = len(lines[0].extra) if lines else 0
    rows = [_model_row(line, frames, metrics, evaluation, s, unit) for line in lines]
    every = [r for line in lines for r in line.runs]
    ref_rows, refs = _reference_rows(every, frames, metrics, evaluation, n_extra, grouped, s, unit)
    marks: list[list[set[str]]] = [[set() for _ in range(n_extra + len(metrics))] for _ in rows + ref_rows]
    skill: dict[str, dict[str, stats.Derived]] = {}
    unsettled: list[str] = []
    for j, metric in enumerate(metrics):
        col = [r.info["samples"][j] for r in rows]
        up = metric in higher
        column_marks, _ = judge_column(col, s, up)
        if any("tie" in mk for mk in column_marks):
            unsettled.append(metric)
        ref_values = [r.values[n_extra + j] for r in ref_rows]
        ref_means = [v.mean for v in ref_values if isinstance(v, Estimate)]
        bar = (max(ref_means) if up else min(ref_means)) if ref_means else None
        best_ref = better_reference(refs, j, up)
        for i, row in enumerate(rows):
            marks[i][n_extra + j] |= column_marks[i]
            v = row.values[n_extra + j]
            if col[i] is not None and judged(col[i]) is None:  # means only: no † either
                continue
            verdict = None
            if judged(col[i]) is not None and best_ref is not None:
                try:
                    verdict = versus_reference(col[i], best_ref, s, up)  # type: ignore[arg-type]
                except ValueError:  # no shared trajectory with the reference
                    verdict = None
            if verdict is not None and not math.isnan(verdict.lo):
                if not beats_reference(verdict):
                    marks[i][n_extra + j].add("noskill")
                if metric in skill_metrics and not up:
                    skill.setdefault(row.name, {})[metric] = verdict
            elif bar is not None and isinstance(v, Estimate) and _no_skill(v, bar, up):
                marks[i][n_extra + j].add("noskill")
    fallback = [r.name for r in rows if r.runs and all(x is None for x in r.info["samples"])]
    return Built(rows + ref_rows, marks, skill, refs, fallback, unsettled)
