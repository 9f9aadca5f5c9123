"""Tune trials resumed from their checkpoints, and what ``sweep gc`` keeps of them.

A trial stopped by a signal (Ctrl-C, SIGTERM: its run KILLED with a
checkpoint) or by a failure of the machine (a full disk, a busy database: a
resumable run FAILED) ends FAIL in the study, as Optuna records any trial
whose function raised; a trial cannot be run again. Before it ends, its
checkpoint is handed to a new trial (Optuna's own pattern for retried trials):
``keep_for_resume`` enqueues the same parameters as a WAITING trial whose user
attributes name the run (``resume_run``), the interrupted trial
(``resumes_trial``) and the cell key (``resume_cell``). The next claim of
any of the study's trial rows (``worker``) starts that trial first; ``resume_from`` continues the same MLflow run
from its checkpoint (its validations before the checkpoint reported again to
the pruner), or, when the checkpoint is not on this machine or the config
changed the cell, trains afresh with those parameters (the old run stays KILLED).

``checkpoint_need`` is ``sweep gc``'s decision for a trial's checkpoint: kept
while a WAITING (or RUNNING) trial of its study resumes it; reclaimable once
no trial will (the resuming one ran, the trial was never handed on, or the
study's parent run FINISHED: its last ``tune`` reached its trials without it).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from ...config import Config
from ...errors import resumable
from ...runs.contract import RunInterrupted, resume_file

log = logging.getLogger(__name__)

ATTR_RUN = "mlflow_run_id"  # a trial's MLflow run (tuning.ATTR_RUN)
ATTR_RESUME_RUN = "resume_run"  # on a trial enqueued to resume: the run whose checkpoint it continues
ATTR_RESUMES = "resumes_trial"  # ... and the number of the trial that was stopped
ATTR_RESUME_CELL = "resume_cell"  # ... and that run's cell key (another config makes another cell: trained afresh)
TAG_RESUMED_TRIAL = "resumed_trial"  # on the MLflow run: the trial it was started by (its ``trial`` tag: the last)


def worth_resuming(exc: BaseException) -> bool:
    """A trial's run stopped in a way ``train --resume`` would continue: a signal (also one that landed before
    training, while resuming), or a failure of the machine."""
    return isinstance(exc, (RunInterrupted, KeyboardInterrupt)) or (isinstance(exc, Exception) and resumable(exc))


def keep_for_resume(cfg: Config, trial: Any, run_id: str | None, cell_key: str) -> bool:
    """Enqueue the stopped ``trial``'s parameters as a WAITING trial that resumes ``run_id`` from its checkpoint;
    False (nothing enqueued) when the run left no checkpoint on this machine."""
    if run_id is None or not resume_file(cfg, run_id).is_file():
        return False
    trial.study.enqueue_trial(dict(trial.params), user_attrs={
        ATTR_RESUME_RUN: run_id, ATTR_RESUMES: trial.number, ATTR_RESUME_CELL: cell_key})
    log.warning("trial %d stopped; its run %s is resumed from its checkpoint by the study's next trial",
                trial.number, run_id)
    return True


def resume_from(cfg: Config, trial: Any, cell_key: str, tags: dict[str, str]) -> str | None:
    """The run this trial continues (its checkpoint is here, its cell is this config's), with the stopped trial's
    reports copied to this one and its number in ``tags`` (``resumed_trial``, for the run); None: a fresh run
    (a trial not enqueued to resume, or one that cannot)."""
    run_id = trial.user_attrs.get(ATTR_RESUME_RUN)
    if not run_id:
        return None
    number = trial.user_attrs.get(ATTR_RESUMES)
    if trial.user_attrs.get(ATTR_RESUME_CELL) != cell_key:
        log.warning("trial %d: trial %s's run %s was of another config (cell key %s, now %s); training afresh",
                    trial.number, number, run_id, trial.user_attrs.get(ATTR_RESUME_CELL), cell_key)
        return None
    if not resume_file(cfg, run_id).is_file():
        log.warning("trial %d: no checkpoint of trial %s's run %s on this machine (%s); training afresh",
                    trial.number, number, run_id, resume_file(cfg, run_id))
        return None
    stopped = next((t for t in trial.study.get_trials(deepcopy=False) if t.number == number), None)
    for step, value in sorted((stopped.intermediate_values if stopped is not None else {}).items()):
        trial.report(value, step)  # the pruner judges the whole curve, not only what follows the checkpoint
    tags[TAG_RESUMED_TRIAL] = str(number)
    return run_id


def checkpoint_need(trials: Sequence[Any], run_id: str, study: str, parent_status: str | None) -> tuple[bool, str]:
    """Whether the checkpoint of trial run ``run_id`` (KILLED or FAILED) is still needed by its study, and why."""
    resumers = [t for t in trials if t.user_attrs.get(ATTR_RESUME_RUN) == run_id]
    waiting = [t for t in resumers if t.state.name == "WAITING"]
    running = [t for t in resumers if t.state.name == "RUNNING"]
    if running:
        return True, f"trial #{running[-1].number} of study {study} is resuming it"
    if waiting and parent_status != "FINISHED":
        return True, (f"the study can resume it: trial #{waiting[-1].number} of study {study} continues it at the "
                      "next `bronchopose tune` of the study")
    if waiting:
        return False, (f"study {study} done (its parent run FINISHED) without resuming it; trial "
                       f"#{waiting[-1].number} would train afresh")
    if resumers:
        t = resumers[-1]
        return False, f"trial #{t.number} of study {study} ({t.state.name}) ran without it"
    own = [t for t in trials if t.user_attrs.get(ATTR_RUN) == run_id]
    if own:
        return False, f"trial #{own[-1].number} of study {study} ended {own[-1].state.name}; no trial resumes it"
    return False, f"no trial of study {study} resumes it"
