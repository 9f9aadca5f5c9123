"""`bronchopose tune`: Optuna hyperparameter search for one cell (``bronchocli.api.tune``), or --show a study's
results (``api.study``)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG, RULES, Arch, BronchoError, Population, PoseFrame, RotLoss
from .common import ConfigOpt, ProfileOpt, SetOpt, ShowFormat, console
from .launcher_flags import given as launcher_options


# tune's own words for the generic launcher options (``launcher_flags`` adds every launcher's options)
HELPS = {"workers": "Local worker processes, placed like a sweep's. Default: GPUs x --per-gpu on a GPU machine, else 1 "
         "(in this process); at most one per trial.",
         "gpus": "GPUs for the local workers, round-robin: auto (the default), none, or a list such as 0,1.",
         "per_gpu": "Trials run at once on each GPU."}


def tune(
    ctx: typer.Context,
    arch: Optional[Arch] = typer.Option(None, "--arch", "-a", help="Architecture."),
    rot_loss: Optional[RotLoss] = typer.Option(None, "--rot-loss", "-l", help="Rotation loss."),
    population: Optional[Population] = typer.Option(None, "--population", "-P", help="Population."),
    fold: Optional[str] = typer.Option(None, "--fold", help="Held-out patient (cross-subject only)."),
    seed: int = typer.Option(0, "--seed", help="Training seed of every trial."),
    pose_frame: Optional[PoseFrame] = typer.Option(None, "--pose-frame", help="Relative-pose frame (default: the "
                                                   "first of the config's grid.pose_frame)."),
    train_trajectories: Optional[int] = typer.Option(None, "--train-trajectories",
                                                     **RULES["train_trajectories"].bounds(),
                                                     help="Training trajectories per patient and lobe."),
    trials: Optional[int] = typer.Option(None, "--trials", "-n", **RULES["trials"].bounds(),
                                         help="Total finished trials of the study (default: tune.trials)."),
    timeout: Optional[float] = typer.Option(None, "--timeout", **RULES["timeout"].bounds(),
                                            help="Stop starting trials after this many seconds."),
    storage: Optional[str] = typer.Option(None, "--storage", help="Study storage URL (default: storage.url)."),
    study: Optional[str] = typer.Option(None, "--study", help="Study name [<config name>-<arch>-<loss>-...]."),
    launcher: Optional[str] = typer.Option(None, "--launcher", help="Where the trials' workers run: local (the "
                                           "default) or slurm (array tasks; `sweep cancel --study` stops them)."),
    show: bool = typer.Option(False, "--show", help="Print the best trial and parameter importances, then exit."),
    fmt: ShowFormat = typer.Option("table", "--format", help="--show output."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Tune one cell's hyperparameters over `tune.space` with Optuna (TPE, seeded), minimising validation loss.

    Every trial is an MLflow run (tags run_kind=trial, study, trial) and a row of the claims
    table (`status --sweep <study>.trials`), claimed by a sweep worker of `--launcher`: local
    processes (`--workers`, `--gpus`, `--per-gpu`) or Slurm array tasks. The pruner stops poor
    trials; the study is resumable. With --show, print the best trial and importances.
    """
    from .. import api  # lazy: keeps `bronchopose --help` fast

    cell = dict(arch=arch, rot_loss=rot_loss, population=population, fold=fold, seed=seed, pose_frame=pose_frame,
                train_trajectories=train_trajectories)
    given = dict(storage=storage, profile=profile, overrides=set_ or (), console=console)
    if show:
        api.study(config, study, fmt=fmt, **cell, **given)
    elif arch is None and rot_loss is None and population is None:
        raise BronchoError("tune needs --arch, --rot-loss and --population (or --show)")
    else:
        api.tune(config, trials=trials, study=study, timeout=timeout, launcher=launcher, progress=not quiet, **cell,
                 **given, **launcher_options(ctx))
