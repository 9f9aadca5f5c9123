"""The work half of the public API: what ``bronchopose train`` and ``bronchopose report`` do, as calls that
return typed results instead of exit codes and printed tables.

Each function takes a config as the commands do (a path to an ``experiments.yaml``, a ``profile`` of it and
``overrides`` in ``--set`` syntax) or an already loaded :class:`~bronchocli.config.Config`, checks what it was
given before any expensive work (one :class:`~bronchocli.errors.BronchoError` line, as the commands print them),
and prints progress only to a ``console`` it is given (``None``: silent). The commands are thin layers over these
functions: flags -> call -> print.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console

from .. import interrupts
from ..config import DEFAULT_CONFIG, Config, load_config, parse_override
from ..config.arguments import checked
from ..errors import BronchoError
from ..pathcheck import check_output

if TYPE_CHECKING:  # the results' modules load their stacks (torch, the reporting stack) only when called
    from ..reporting.report import ReportResult
    from ..sweep.status import SweepState
    from ..training.outcome import TrainResult
    from .results import StudyResult, SweepResult

ConfigLike = str | os.PathLike | Config


@checked
def config_of(config: ConfigLike = DEFAULT_CONFIG, profile: str | None = None,
              overrides: Sequence[str] = ()) -> Config:
    """The config ``config`` names (a file, with ``profile`` and ``--set``-style ``overrides``), or the given one
    with the overrides applied."""
    if isinstance(config, Config):
        if profile is not None:
            raise BronchoError("profile: only with a config file (a loaded Config already chose its profile)")
        return config.with_values(dict(parse_override(s) for s in overrides)) if overrides else config
    return load_config(Path(config), profile, tuple(overrides))


def _unguarded(call: str) -> None:
    """A worker process (``spawn``) re-imports the script that started it; a script that calls ``api.sweep`` or
    ``api.tune`` at its top level would start a sweep again inside each worker. There: one line saying what to
    add, and that worker exits 2 (its sweep's other output says the worker stopped on an error)."""
    main = sys.modules.get("__main__")
    if getattr(main, "__name__", None) != "__mp_main__":
        return
    script = getattr(main, "__file__", None) or "your script"
    print(f"error: {call} was called while a worker process imported {script}: put the call under "
          '`if __name__ == "__main__":` (worker processes import the script that started them; docs/api.md)',
          file=sys.stderr, flush=True)
    raise SystemExit(2)


def _silent() -> Console:
    return Console(quiet=True)


@checked
def train(config: ConfigLike = DEFAULT_CONFIG, *, arch: str, rot_loss: str, population: str,
          fold: str | None = None, seed: int = 0, pose_frame: str | None = None,
          train_trajectories: int | None = None, profile: str | None = None, overrides: Sequence[str] = (),
          use_tuned: str | None = None, resume: bool | str = False, again: bool = False, progress: bool = False,
          console: Console | None = None, resumed_by: Callable[[str], str] | None = None) -> TrainResult:
    """Train and evaluate one cell as one MLflow run, as ``bronchopose train`` does.

    ``resume``: ``True`` continues the cell's latest KILLED/FAILED run from its checkpoint, a run id that run.
    ``use_tuned``: apply the best trial of this Optuna study first. ``resumed_by(run_id)``: the call that resumes a
    run, which a stopped or resumably failed run's line names (default ``api.train(..., resume='<id>')``; the
    command line passes its own command with ``--resume --run-id``). A cell that already has a FINISHED run is
    not trained again unless ``again`` (``result.trained`` is then False and ``result.run`` is that run).
    Returns a :class:`~bronchocli.training.outcome.TrainResult`: ``run_id``, ``ok``, ``metrics``, ``errors()``,
    ``headline`` (pair position error ÷ the training mean's) and ``summary()``. Inside a launcher's job (a Slurm
    batch job) the run also stops, and checkpoints, on that launcher's warning signal (``launchers.detected``); outside
    one, SIGUSR1 stops it as SIGTERM does (never a silent kill that leaves the run RUNNING).
    """
    from ..sweep.launchers import detected  # lazy: the sweep stack (and torch) load only when training
    from ..training import entry

    cfg = config_of(config, profile, overrides)
    cell = cfg.cell(arch=arch, rot_loss=rot_loss, population=population, fold=fold, seed=seed,
                    pose_frame=pose_frame, train_trajectories=train_trajectories)
    if use_tuned:
        from ..sweep.tuning.studies import apply_best  # lazy: optuna only with use_tuned

        cfg = apply_best(cfg, use_tuned)
        cell = cfg.cell(**cell.coords())  # tuned values change what the run computes: a new key
    env = detected()  # a launcher's job: its warning signal; else SIGUSR1 stops `train` as SIGTERM does
    warning = (env.warning_signal, env.warning_meaning) if env and env.warning_signal else \
        (getattr(signal, "SIGUSR1", None), interrupts.UNWARNED_USR1)
    with interrupts.stopped_by(*warning):
        return entry.train(cfg, cell, resume=resume, progress=progress, again=again, console=console or _silent(),
                           resumed_by=resumed_by)


@checked
def report(config: ConfigLike = DEFAULT_CONFIG, *, table: str = "all", evaluation: str = "both",
           fmt: str = "both", out: str | os.PathLike = "reports", sweep: str | None = None,
           pose_frame: str | None = None, include_other_configs: bool = False, best: int = 0,
           figures: bool | None = None, trajectories: int = 4, latency: bool = True,
           latency_from: str | os.PathLike | None = None, latency_device: str = "cpu",
           image_size: int | None = None, to_parent: bool = True, profile: str | None = None,
           overrides: Sequence[str] = (), console: Console | None = None,
           err_console: Console | None = None, quiet: bool = False) -> ReportResult:
    """Build the paper's tables (and figures) from the FINISHED runs of the config's cells and write them to
    ``out``, as ``bronchopose report`` does (docs/reports.md).

    ``table``: ``all`` or one table name (personalized, cross-subject, sota, ablation, frames, tracking);
    ``evaluation``: ``pair``, ``accumulated`` or ``both``; ``fmt``: ``md``, ``latex`` or ``both``; ``figures``:
    default only with ``table="all"``. Returns a :class:`~bronchocli.reporting.report.ReportResult`: its
    ``tables`` (``table(key)`` finds one, ``Table.frame()`` gives it as a pandas DataFrame), the ``files``
    written and the ``warnings``. With a ``console`` the tables and progress are printed as the command prints
    them (``quiet``: only the summary lines).
    """
    from ..reporting import entry  # lazy: the reporting stack loads only when reporting
    from ..reporting import report as rep
    from ..reporting import tables as tbl
    from ..reporting.report import profiles_from_json

    names, evals, suffixes = tbl.table_names(table), tbl.evaluations(evaluation), rep.output_suffixes(fmt)
    folder = Path(out).expanduser()
    check_output(folder, "--out", "folder")  # before minutes of work, not after
    given_profiles = profiles_from_json(Path(latency_from)) if latency_from is not None else None
    cfg = config_of(config, profile, overrides)
    return entry.report(cfg, names, evals, suffixes, folder, sweep=sweep, pose_frame=pose_frame,
                        include_other_configs=include_other_configs, best=best,
                        figures=table == "all" if figures is None else figures, trajectories=trajectories,
                        profiles=given_profiles, latency=latency, latency_device=latency_device,
                        image_size=image_size, quiet=quiet or console is None, to_parent=to_parent,
                        console=console or _silent(), err_console=err_console or console or _silent())


@checked
def status(config: ConfigLike = DEFAULT_CONFIG, *, sweep: str | None = None, show_all: bool = False,
           repair: bool = False, storage: str | None = None, profile: str | None = None,
           overrides: Sequence[str] = (), console: Console | None = None) -> SweepState:
    """The state of a sweep (default: the config's), as ``bronchopose status`` shows it (``repair``: first end the
    runs a dead process left RUNNING and repair damaged claims rows, as ``status --repair``).

    Returns a :class:`~bronchocli.sweep.status.SweepState`: ``cells()`` gives one ``CellOutcome`` per cell
    (label, key, state, attempts, run id, failure reason, its run's metrics and ``headline``), ``before`` and
    ``after`` the lines the command prints around its table.
    """
    from ..sweep import entry  # lazy: the sweep stack loads only when asked

    cfg = config_of(config, profile, overrides)
    if storage:
        cfg = cfg.with_values({"storage.url": storage})
    return entry.status(cfg, sweep or cfg.name, show_all=show_all, repair=repair, console=console or _silent())


def _target(cfg: Config, arch: str | None, rot_loss: str | None, population: str | None, **coords: Any):
    if arch is None and rot_loss is None and population is None:
        return None
    if arch is None or rot_loss is None or population is None:
        raise BronchoError("tune needs all of --arch, --rot-loss and --population (or --show --study NAME)")
    return cfg.cell(arch=arch, rot_loss=rot_loss, population=population, **coords)


@checked
def tune(config: ConfigLike = DEFAULT_CONFIG, *, arch: str, rot_loss: str, population: str,
         fold: str | None = None, seed: int = 0, pose_frame: str | None = None,
         train_trajectories: int | None = None, trials: int | None = None, timeout: float | None = None,
         storage: str | None = None, study: str | None = None, launcher: str | None = None, progress: bool = False,
         profile: str | None = None, overrides: Sequence[str] = (), console: Console | None = None,
         **launcher_options: Any) -> StudyResult:
    """Tune one cell's hyperparameters over ``tune.space`` with Optuna, as ``bronchopose tune`` does: the study
    (shared storage, resumable) runs to ``trials`` trial rows done (default ``tune.trials``), each row claimed by
    a worker of ``launcher`` (default local: ``workers`` processes here on ``gpus``, one worker and no GPU in this
    process; ``"slurm"``: array tasks, which load the config file); ``launcher_options``: the options that
    launcher's ``parameters`` declare, as typed values (``workers=2``, ``ssh_hosts=["a", "b"]``); returns the
    study's :class:`~bronchocli.api.results.StudyResult` (best trial, importances)."""
    _unguarded("api.tune")
    from ..sweep import entry  # lazy: optuna only when tuning
    from ..sweep.task import TaskSpec
    from .results import StudyResult

    cfg = config_of(config, profile, overrides)
    if storage:
        cfg = cfg.with_values({"storage.url": storage})
    target = _target(cfg, arch, rot_loss, population, fold=fold, seed=seed, pose_frame=pose_frame,
                     train_trajectories=train_trajectories)
    kind = entry.launcher_kind(cfg, launcher or entry.TUNE_LAUNCHER)
    options = entry.launcher_options(kind, launcher_options, "api.tune")
    spec = None if isinstance(config, Config) else TaskSpec(config=str(config), profile=profile,
                                                             overrides=tuple(overrides), storage=storage)
    info = entry.tune(cfg, target, trials=trials, study=study, timeout=timeout, kind=kind, options=options,
                      spec=spec, progress=progress, console=console or _silent())
    return StudyResult.from_info(info)


@checked
def study(config: ConfigLike = DEFAULT_CONFIG, name: str | None = None, *, arch: str | None = None,
          rot_loss: str | None = None, population: str | None = None, fold: str | None = None, seed: int = 0,
          pose_frame: str | None = None, train_trajectories: int | None = None, storage: str | None = None,
          fmt: str = "table", profile: str | None = None, overrides: Sequence[str] = (),
          console: Console | None = None) -> StudyResult:
    """A stored study's state, as ``bronchopose tune --show`` prints it: ``name``, or the study of the cell
    (``arch``, ``rot_loss``, ``population``, ...). No training."""
    from ..sweep import entry  # lazy: optuna only when a study is read
    from .results import StudyResult

    if fmt not in ("table", "json"):
        raise BronchoError(f"--format {fmt!r}: must be table or json")
    cfg = config_of(config, profile, overrides)
    if storage:
        cfg = cfg.with_values({"storage.url": storage})
    target = _target(cfg, arch, rot_loss, population, fold=fold, seed=seed, pose_frame=pose_frame,
                     train_trajectories=train_trajectories)
    return StudyResult.from_info(entry.show_study(cfg, name, target, fmt, console or _silent()))


@checked
def sweep(config: str | os.PathLike = DEFAULT_CONFIG, *, only: Sequence[str] = (), launcher: str | None = None,
          retry_failed: bool = False, detach: bool = False, storage: str | None = None,
          use_tuned: str | None = None, runner: str | None = None, profile: str | None = None,
          overrides: Sequence[str] = (), console: Console | None = None, **launcher_options: Any) -> SweepResult:
    """Run the config's plan, each cell once, as ``bronchopose sweep run`` does: with the local launcher
    (``workers`` processes here, placed on ``gpus``) or another (``launcher="slurm"``; ``detach``: return once
    submitted). ``launcher_options``: the options the launcher's ``parameters`` declare, as typed values
    (``workers=2, gpus="0,1", per_gpu=2``; a plugin's ``ssh_hosts=["a", "b"]``); one the launcher does not take
    is one line naming the launchers that do. ``only``: ``--only`` selections (``key=value[,value];...``). The
    config is a file: the workers load it themselves, as every Slurm array task does.

    Returns a :class:`~bronchocli.api.results.SweepResult`: ``exit_code``/``ok`` and ``state`` (the sweep's
    ``SweepState`` afterwards, read when first asked).
    """
    _unguarded("api.sweep")
    from ..sweep import entry  # lazy: the sweep stack loads only when sweeping
    from ..sweep.task import TaskSpec
    from .results import SweepResult

    if isinstance(config, Config):
        raise BronchoError("sweep: needs the config file, not a loaded Config (each worker loads the file itself)")
    spec = TaskSpec(config=str(config), profile=profile, overrides=tuple(overrides), storage=storage,
                    use_tuned=use_tuned, only=tuple(only), runner=runner)
    cfg = spec.load()  # as every Slurm array task loads it
    spec.selection()  # a bad --only or --runner: one line before anything else
    spec.cell_runner()
    kind = entry.launcher_kind(cfg, launcher)
    options = entry.launcher_options(kind, launcher_options, "api.sweep")
    if detach and not kind.Session.outlives_command:
        raise BronchoError(f"--detach: launcher {kind.name} runs its workers in this command; only a launcher "
                           "whose workers outlive it (slurm) can detach")
    code = entry.run(cfg, spec, kind, options=options, detach=detach, retry_failed=retry_failed,
                     console=console or _silent())
    return SweepResult(code, lambda: entry.status(cfg, cfg.name, console=_silent()))
