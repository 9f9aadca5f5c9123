"""Which run of a cell ``train --resume`` continues, and what ``train`` says about it: advice that holds.

Every line a ``train`` prints about continuing a run is the call that does it. A door declares how it is called
(``resumed_by``: ``bronchopose train`` gives its own flags with ``--resume --run-id RUN``; the Python API's
default is ``api.train(..., resume='RUN')``), and ``advised`` rewrites a stopped or failed run's one line with
it: "run the same command again" is said only where the same command really does it (no checkpoint yet: a new
run starts from step 0). A fresh ``train`` of a cell whose KILLED/FAILED run has a checkpoint is refused
(``refuse_fresh``: that run and the command that resumes it; ``--again`` trains a new run anyway), and a
``--resume`` that finds no run of this cell key but one of the same coordinates made with other settings names
that run and the settings that differ (``find_resumable``).
"""

from __future__ import annotations

import copy
import os
import re
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

import yaml

from ..cells import Cell
from ..config import Config
from ..config.grid import NOT_IN_KEY, RUN_SECTIONS
from ..errors import BronchoError, resumable
from ..runs.contract import RunInterrupted, resume_file
from ..runs.records import TAG_CELL_KEY, TAG_FAILURE, flatten, search_runs

# The phrases of a run's one line that promise the same command resumes it (checkpoint.py, runs/client.py): true
# for `sweep run` (its worker resumes the cell's run), not for `train`, which needs --resume.
AGAIN = re.compile(r"run the same command again(?:: it resumes the run from its (?:last )?checkpoint"
                   r"| \(an unfinished run resumes from its checkpoint\))?")
STOPPED = ("KILLED", "FAILED")
_HOW: ContextVar[Callable[[str], str] | None] = ContextVar("resume_how", default=None)


@contextmanager
def resumed_by(how: Callable[[str], str]) -> Iterator[None]:
    """Inside: ``how(run_id)`` is the call that resumes ``run_id`` at this door (the command line's own)."""
    token = _HOW.set(how)
    try:
        yield
    finally:
        _HOW.reset(token)


def how(run_id: str) -> str:
    """The call that resumes ``run_id``, quoted: the door's (``resumed_by``), else the Python API's."""
    door = _HOW.get()
    return f"`{door(run_id)}`" if door is not None else f"`api.train(..., resume={run_id!r})`"


def has_checkpoint(cfg: Config, run_id: str) -> bool:
    return resume_file(cfg, run_id).is_file()


def can_resume(cfg: Config, run_id: str, status: str, reason: str | BaseException | None) -> bool:
    """A stopped run that ``train --resume`` continues: its checkpoint is here, and it was KILLED (a signal,
    an outage) or FAILED for a reason of the machine (``errors.resumable``)."""
    if status not in STOPPED or not has_checkpoint(cfg, run_id):
        return False
    return status == "KILLED" or isinstance(reason, RunInterrupted) or (reason is not None and resumable(reason))


def advised(exc: BronchoError, cfg: Config) -> BronchoError:
    """``exc`` (raised out of a run: ``exc.run_id``) with its advice made true for this door: the call that
    resumes the run where it can be resumed, else the same command (a new run) where the line promised a resume."""
    run_id = getattr(exc, "run_id", None)
    text = str(exc)
    if run_id is None:
        return exc
    if can_resume(cfg, run_id, "KILLED" if isinstance(exc, RunInterrupted) else "FAILED", exc):
        advice = f"resume it with {how(run_id)}"
    elif AGAIN.search(text):
        advice = "run the same command again (the run left no checkpoint: a new run starts from step 0)"
    else:
        return exc
    out = copy.copy(exc)  # same class, attributes (run_id, signal) and exit code
    out.args = (AGAIN.sub(advice, text, count=1) if AGAIN.search(text) else f"{text}; {advice}",)
    return out


def stopped_runs(client: Any, exp_id: str, cell: Cell) -> list[Any]:
    """This cell key's KILLED/FAILED runs, newest first."""
    return search_runs(client, [exp_id], {TAG_CELL_KEY: cell.key}, STOPPED)


def resumable_run(cfg: Config, client: Any, exp_id: str, cell: Cell) -> Any | None:
    """This cell key's newest KILLED/FAILED run that ``train --resume`` continues (``can_resume``), or None."""
    for run in stopped_runs(client, exp_id, cell):
        if can_resume(cfg, run.info.run_id, run.info.status, run.data.tags.get(TAG_FAILURE)):
            return run
    return None


def refusal(cfg: Config, cell: Cell, run: Any) -> BronchoError:
    """The one line refusing a fresh ``train`` of ``cell`` while its stopped ``run`` can be resumed."""
    rid = run.info.run_id
    return BronchoError(f"cell {cell.label} (key {cell.key}) has a {run.info.status} run {rid} with a checkpoint "
                        f"({resume_file(cfg, rid)}): {how(rid)} resumes it; --again trains a new run from step 0 "
                        "instead (that run stays as it is)")


def fresh_note(run: Any) -> str:
    """What ``train --again`` says when it starts a new run beside a resumable one."""
    rid = run.info.run_id
    return f"note: --again: a new run from step 0; the {run.info.status} run {rid} keeps its checkpoint ({how(rid)} " \
           "resumes it)"


def find_resumable(cfg: Config, client: Any, exp_id: str, cell: Cell) -> str:
    """The run ``train --resume`` continues: this cell key's latest KILLED/FAILED (or RUNNING, its process gone)
    run; else one line, naming a run of the same coordinates made with other settings and what differs."""
    runs = search_runs(client, [exp_id], {TAG_CELL_KEY: cell.key}, [*STOPPED, "RUNNING"])
    if runs:
        return runs[0].info.run_id
    missing = f"--resume: no KILLED/FAILED run of cell {cell.label} (key {cell.key}) to resume"
    other = _same_coordinates(client, exp_id, cell)
    if other is None:
        raise BronchoError(missing)
    rid, key = other.info.run_id, other.data.tags.get(TAG_CELL_KEY)
    raise BronchoError(f"{missing}: its {other.info.status} run {rid} (key {key}) was made with other settings: "
                       f"{differences(cfg, client, rid)}; resume it with the settings it was made with "
                       "(the same --config, --profile, --set and --use-tuned), or train without --resume to start "
                       "a new run")


def _same_coordinates(client: Any, exp_id: str, cell: Cell) -> Any | None:
    """The newest KILLED/FAILED run of the same coordinates as ``cell`` under another cell key, or None."""
    given = {k: v for k, v in cell.tags().items() if v}  # MLflow keeps no empty tag: an unset field is absent
    for run in search_runs(client, [exp_id], given, STOPPED):
        tags = run.data.tags
        if tags.get(TAG_CELL_KEY) and all((tags.get(k) or "") == v for k, v in cell.tags().items()):
            return run
    return None


def differences(cfg: Config, client: Any, run_id: str) -> str:
    """``train.lr 0.001 (now 0.0003), …``: the run-defining settings (those of the cell key) in which the run's
    saved config.yaml differs from ``cfg``."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # no tqdm bar on a one-line error
    try:
        with tempfile.TemporaryDirectory() as tmp:
            theirs = yaml.safe_load(Path(client.download_artifacts(run_id, "config.yaml", tmp)).read_text())
    except Exception as exc:  # noqa: BLE001 - MLflow's own types; the run may have stopped before logging it
        return f"its config.yaml could not be read ({type(exc).__name__})"
    ours, old = _signature(cfg.dump()), _signature(theirs or {})
    diff = [f"{k} {old.get(k, '(unset)')} (now {ours.get(k, '(unset)')})"
            for k in sorted(set(ours) | set(old)) if ours.get(k) != old.get(k)]
    return ", ".join(diff) if diff else "none found in its config.yaml (this version computes cell keys otherwise)"


def _signature(data: dict[str, Any]) -> dict[str, str]:
    sig = {k: data.get(k) or {} for k in RUN_SECTIONS}
    for section, key in NOT_IN_KEY:
        if isinstance(sig.get(section), dict):
            sig[section] = {k: v for k, v in sig[section].items() if k != key}
    return flatten(sig)
