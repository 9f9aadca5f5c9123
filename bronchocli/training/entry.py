"""``bronchopose train`` as a library call: check the paths, make sure the dataset exists, run one cell, return
its run (``outcome.TrainResult``; the command exits 0 when FINISHED, 1 otherwise)."""

from __future__ import annotations

from collections.abc import Callable

from rich.console import Console

from .. import urls
from ..cells import Cell
from ..config import Config, check_paths
from ..errors import BronchoError
from ..generation import ensure_dataset
from ..runs.client import check_reachable, client_for
from ..runs.contract import RunResult
from ..runs.records import finished_cell_runs
from . import resumable
from .once import cell_turn
from .outcome import TrainResult
from .run import run_cell


def finished_run(cfg: Config, cell: Cell) -> str | None:
    """The id of a FINISHED MLflow run of ``cell`` (MLflow is the record of what finished), else None. A SQLite
    store not created yet holds none; otherwise the store is opened as training opens it (relocated or refused)."""
    db = urls.sqlite_file(cfg.paths.mlflow_uri)
    if db is not None and not db.is_file():
        return None
    client = client_for(cfg)
    exp = client.get_experiment_by_name(cfg.experiment_name)
    run = finished_cell_runs(client, exp.experiment_id, cfg.name, [cell.key]).get(cell.key) if exp else None
    return run.info.run_id if run is not None else None


def check_fresh(cfg: Config, cell: Cell, again: bool, say: Callable[[str], None]) -> None:
    """A fresh run of a cell whose KILLED/FAILED run has a checkpoint is refused (one line: that run and the call
    that resumes it); ``again`` trains a new run anyway, saying which run stays."""
    db = urls.sqlite_file(cfg.paths.mlflow_uri)
    if db is not None and not db.is_file():
        return
    client = client_for(cfg)
    exp = client.get_experiment_by_name(cfg.experiment_name)
    run = resumable.resumable_run(cfg, client, exp.experiment_id, cell) if exp else None
    if run is not None and not again:
        raise resumable.refusal(cfg, cell, run)
    if run is not None:
        say(resumable.fresh_note(run))


def train(cfg: Config, cell: Cell, *, resume: str | bool = False, progress: bool = True, again: bool = False,
          console: Console, resumed_by: Callable[[str], str] | None = None) -> TrainResult:
    """Train and evaluate ``cell`` as one MLflow run (``resume``: continue its latest, or this, KILLED/FAILED run
    from its checkpoint). A cell with a FINISHED run is not trained again unless ``again`` (the result says
    ``trained=False`` and carries that run); a ``train`` of the same cell in progress is waited for first
    (``once.cell_turn``), so two started together train it once. ``console`` gets the progress lines; the
    result's ``summary()`` is the closing line. ``resumed_by(run_id)``: the call its lines name to resume a run
    (``resumable.how``)."""
    if resumed_by is not None:
        with resumable.resumed_by(resumed_by):
            return train(cfg, cell, resume=resume, progress=progress, again=again, console=console)
    if cfg.tune.applied:
        console.print(f"hyperparameters from {cfg.tune.applied}")
    check_paths(cfg)  # one line before anything is created
    check_reachable(cfg)  # a dead MLflow server or database: one line within runs.timeout_s, nothing created
    with cell_turn(cfg, cell, lambda text: console.print(text, highlight=False)):  # one `train` of a cell at a time
        done = None if again or resume else finished_run(cfg, cell)
        if done is not None:
            run = client_for(cfg).get_run(done)
            return TrainResult(cell, cfg.experiment_name, RunResult(done, run.info.status, dict(run.data.metrics)),
                               trained=False)
        if not resume:
            check_fresh(cfg, cell, again, lambda text: console.print(text, highlight=False))
        ensure_dataset(cfg)
        console.print(f"[bold]train[/] {cell.label}  (cell {cell.key}, experiment {cfg.experiment_name})")
        try:
            result = run_cell(cfg, cell, resume=resume, progress=progress, reachable=True)  # checked above
        except BronchoError as exc:  # a stopped or failed run: its line says how to resume it, at this door
            raise resumable.advised(exc, cfg) from None
    if result.stop_requested:
        console.print("[yellow]interrupt received during evaluation: the run was completed first[/]")
    return TrainResult(cell, cfg.experiment_name, result)
