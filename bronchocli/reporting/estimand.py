"""What a table's intervals and tests are about, stated in its caption: the estimand, the bounds, refusals.

* **These patients** (personalized tables, Table 6, the ablation, the tracking
  table): the mean over new seeds and new test trajectories of the patients
  tested. It does not generalise to a new patient.
* **A new patient** (cross-subject tables, and the frames table when its runs
  are cross-subject): the mean over new seeds, new patients and their
  trajectories. Patients are a level of the variance (seed, patient,
  trajectory within patient; ``stats.Sample.unit``), so the caption says how
  many patients it rests on.

A row whose sample ``stats.refusal`` refuses (2 seeds; fewer than
``stats.MIN_PATIENTS`` patients for a new-patient estimand) shows its mean
only: no interval, no best/tie mark, no † and no skill; the caption says why.
Each metric's interval keeps the figure inside its bounds (``scale_of``):
percentages (CTF) on the logit scale, positive errors on the log scale.
"""

from __future__ import annotations

from typing import Sequence

from .. import registry
from .stats import MIN_PATIENTS, MIN_SEEDS, PATIENT, PERCENT, POSITIVE, TRAJECTORY, Sample
from .table_model import Row

ESTIMAND_NAMES = {TRAJECTORY: "these patients", PATIENT: "a new patient"}


def unit_of(population: str) -> str:
    """The sampling unit of a table's claim: a new patient for cross-subject, these patients otherwise."""
    return PATIENT if population == "cross-subject" else TRAJECTORY


def scale_of(metric: str) -> str:
    """The scale an interval of ``metric`` is built on (stats.interval): logit for a share in % (a metric
    registered with unit "%", registry.py: CTF), log otherwise."""
    return PERCENT if metric in registry.metric_names() and registry.metric(metric).unit == "%" else POSITIVE


def _samples(rows: Sequence[Row]) -> list[Sample]:
    return [s for r in rows if r.kind == "model" for s in r.info.get("samples", ()) if s is not None]


def _names(patients: Sequence[str]) -> str:
    shown = ", ".join(patients[:6]) + (f" and {len(patients) - 6} more" if len(patients) > 6 else "")
    return f"{len(patients)} patient{'s' if len(patients) != 1 else ''} ({shown})"


def estimand_text(unit: str, rows: Sequence[Row]) -> str:
    """The caption's statement of what every interval and test of the table is about, and on how many patients
    it rests."""
    patients = sorted({k[0] for s in _samples(rows) for k in s.keys})
    if not patients:
        return ""
    reps = {r.info.get("replicates") for r in rows if r.kind == "model" and r.info.get("replicates")}
    if reps == {1}:  # one seed everywhere: the estimand is the trained model, said once
        over = (f"new test trajectories of the {_names(patients)} tested" if unit == TRAJECTORY else
                f"new patients and their trajectories (it rests on {_names(patients)})")
        return (f"Estimand: the one trained model of each row (one seed) — every interval and test is about its "
                f"mean over {over}; seed-to-seed variation is not measured, so it is not a claim about new seeds.")
    if unit == TRAJECTORY:
        return (f"Estimand: these patients — every interval and test is about the mean over new seeds and new test "
                f"trajectories of the {_names(patients)} tested (seeds and trajectories are the variance levels); "
                f"it is not a claim about a new patient.")
    text = (f"Estimand: a new patient — every interval and test is about the mean over new seeds, new patients and "
            f"their trajectories; patients are a variance level (seed, patient, trajectory within patient), so "
            f"it rests on {_names(patients)}")
    if len(patients) < MIN_PATIENTS:
        return (text + f": too few to measure how patients differ (a new-patient interval needs >= {MIN_PATIENTS}), "
                       "so the cells show means only, without interval or marks.")
    return text + (", and is wide with so few." if len(patients) < 10 else ".")


def refused_text(rows: Sequence[Row]) -> str:
    """Which rows show means only because their replicates are too few (2 seeds), and why."""
    by_seeds = [r for r in rows if r.kind == "model" and 1 < (r.info.get("replicates") or 0) < MIN_SEEDS]
    if not by_seeds:
        return ""
    models = [r for r in rows if r.kind == "model" and r.runs]
    which = "every row" if len(by_seeds) == len(models) else ", ".join(r.name for r in by_seeds)
    n = sorted({r.info["replicates"] for r in by_seeds})
    return (f"Means only at {'/'.join(map(str, n))} seeds ({which}): no interval, no best or tie mark and no † — "
            f"with 2 seeds a 95% interval holds the mean 89% of the time and the tests find differences that are "
            f"not there too often (docs/reports.md); these need >= {MIN_SEEDS} seeds.")
