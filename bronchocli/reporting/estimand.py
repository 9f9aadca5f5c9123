"""What a table's intervals and tests are about, stated in its caption: the estimand, the bounds, refusals.

* **These patients** (personalized tables, Table 6, the ablation, the tracking
  table): the mean over new seeds and new test trajectories of the patients
  tested. It does not generalise to a new patient.
* **A new patient** (cross-subject tables, and the frames table when its runs
  are cross-subject): the mean over new seeds, new patients and their
  trajectories. Patients are a level of the variance (seed, patient,
  trajectory within patient; ``stats.Sample.unit``), so the caption says how
  many patients it rests on.

A row with fewer than ``stats.MIN_SEEDS`` seeds (1 or 2) cannot measure how
seeds differ: its estimand is its trained models (``Sample.seeds_fixed``: the
seeds' errors averaged per trajectory, the interval over new test units only),
said in the caption when every row is so, else in a note (captions.fixed_seeds_note).
A row whose sample ``stats.refusal`` refuses (fewer than ``stats.MIN_PATIENTS``
patients for a new-patient estimand) shows its mean only: no interval, no
best/tie mark, no † and no skill.
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


def patients_of(rows: Sequence[Row]) -> list[str]:
    """The patients the model rows' per-trajectory samples rest on, sorted (none: the rows have no samples)."""
    return sorted({k[0] for s in _samples(rows) for k in s.keys})


def _names(patients: Sequence[str]) -> str:
    shown = ", ".join(patients[:4]) + (f" and {len(patients) - 4} more" if len(patients) > 4 else "")
    return f"{len(patients)} patient{'s' if len(patients) != 1 else ''} ({shown})"


def estimand_phrase(unit: str, rows: Sequence[Row]) -> str:
    """The caption's estimand in words (what every interval and test of the table is about) and how many
    patients it rests on: "for new seeds and new test trajectories of these 3 patients (p00, p01, p02), not a
    new patient"."""
    patients = patients_of(rows)
    if not patients:
        return ""
    reps = {r.info.get("replicates") for r in rows if r.kind == "model" and r.info.get("replicates")}
    if reps and max(reps) < MIN_SEEDS:  # too few seeds everywhere: the estimand is the trained models, said once
        over = (f"new test trajectories of these {_names(patients)}" if unit == TRAJECTORY else
                f"new patients (resting on {_names(patients)})")
        if reps == {1}:
            return f"about the one trained model of each row (one seed, not new seeds) on {over}"
        n = "/".join(map(str, sorted(reps)))
        return (f"about the trained models of each row ({n} seeds, fixed: not new seeds; too few to measure how "
                f"seeds differ) on {over}")
    if unit == TRAJECTORY:
        return f"for new seeds and new test trajectories of these {_names(patients)}, not a new patient"
    text = f"for a new patient (new seeds, patients and trajectories), resting on {_names(patients)}"
    if len(patients) < MIN_PATIENTS:
        return text + ": too few to measure how patients differ, so the cells show means only"
    return text + (", hence wide" if len(patients) < 10 else "")
