"""A tuning study's trial rows in the claims table, by name: what ``launch`` adds and ``worker`` claims.

A study of N trials is N rows: sweep ``<study>.trials`` (``study_sweep``; the
suffix keeps them apart from every config's own cells), keys ``trial-0000``,
``trial-0001``, ... (``trial_key``), coordinates the study's target cell plus
the slot, labels ``trial 7 · <cell label>`` (``cells.TrialCell``). A worker is
told to work them by a ``StudyTask`` (light: no Optuna here, the sweep's
command and every worker import it).
"""

from __future__ import annotations

from dataclasses import dataclass

from ...cells import Cell, TrialCell

TRIALS_SUFFIX = ".trials"


def study_sweep(study: str) -> str:
    """The claims table's sweep name of a study's trial rows (and of its launcher's jobs)."""
    return f"{study}{TRIALS_SUFFIX}"


def trial_key(slot: int) -> str:
    return f"trial-{slot:04d}"


def trial_cell(target: Cell, slot: int) -> TrialCell:
    """Trial slot ``slot`` of the study of ``target``."""
    return TrialCell(**target.coords(), trial=slot, key=trial_key(slot))


@dataclass(frozen=True)
class StudyTask:
    """What a worker of a study runs instead of a sweep's stages (picklable: local workers get it by spawn)."""

    study: str  # the Optuna study; its rows are ``study_sweep(study)``
    config: str  # the config's own name (a launcher's config is named after the study's rows: its jobs are found so)
    deadline: float | None = None  # epoch seconds (``tune --timeout``): no trial starts after it
    progress: bool = False  # progress bars: a worker in the command's own process (a worker process logs without)
