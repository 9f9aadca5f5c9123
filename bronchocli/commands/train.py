"""`bronchopose train`: train and evaluate one grid cell as one MLflow run (``bronchocli.api.train``)."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG, RULES, Arch, BronchoError, Population, PoseFrame, RotLoss
from .common import ConfigOpt, ProfileOpt, SetOpt, console


def train(
    arch: Arch = typer.Option(..., "--arch", "-a", help="Architecture."),
    rot_loss: RotLoss = typer.Option(..., "--rot-loss", "-l", help="Rotation loss."),
    population: Population = typer.Option(..., "--population", "-P", help="Population."),
    fold: Optional[str] = typer.Option(None, "--fold", help="Held-out patient (cross-subject only)."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the run."),
    pose_frame: Optional[PoseFrame] = typer.Option(None, "--pose-frame", help="Relative-pose frame (default: the "
                                                   "first of the config's grid.pose_frame)."),
    train_trajectories: Optional[int] = typer.Option(None, "--train-trajectories",
                                                     **RULES["train_trajectories"].bounds(),
                                                     help="Training trajectories per patient and lobe (default: "
                                                     "splits.train)."),
    resume: bool = typer.Option(False, "--resume", help="Continue this cell's latest KILLED/FAILED run from its checkpoint."),
    run_id: Optional[str] = typer.Option(None, "--run-id", help="With --resume: the MLflow run to continue."),
    use_tuned: Optional[str] = typer.Option(None, "--use-tuned", help="Apply the best trial of this Optuna study."),
    again: bool = typer.Option(False, "--again", help="Train a new run even when the cell already has a FINISHED "
                               "run, or a KILLED/FAILED one that --resume would continue."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Train one (arch, rot_loss, population, fold, seed, pose_frame) cell and evaluate it on its test split.

    Generates the configured dataset first if it does not exist. Progress is shown
    per optimiser step; the run, its metrics (per pair and accumulated, with the
    zero-motion and training-mean references), the resolved config, split manifest,
    predictions, per-trajectory errors, trajectory plot and weights land in MLflow
    (`bronchopose ui`). Ctrl-C stops after the current step, saves a checkpoint and
    marks the run KILLED; the line it ends with is the command that resumes it (`--resume --run-id`).
    A cell that already has a FINISHED run (in MLflow) is not trained again unless `--again`; one
    whose KILLED/FAILED run has a checkpoint is not started afresh either: `--resume` continues
    that run, `--again` trains a new one beside it. One `train` of a cell at a time:
    a second `train` of the same cell waits for the first to end (saying so), then reports
    its FINISHED run instead of training again (`--again`: trains another run after it).
    Exit code 1 when the run FAILED.
    """
    from .. import api  # lazy: torch loads only when the command runs

    if run_id and not resume:
        raise BronchoError("--run-id: only meaningful with --resume")
    flags = ["-c", str(config), "-a", arch, "-l", rot_loss, "-P", population, *(["--fold", fold] if fold else []),
             "--seed", str(seed), *(["--pose-frame", pose_frame] if pose_frame else []),
             *(["--train-trajectories", str(train_trajectories)] if train_trajectories else []),
             *(["--profile", profile] if profile else []), *[a for s in set_ or () for a in ("--set", s)],
             *(["--use-tuned", use_tuned] if use_tuned else []), *(["--quiet"] if quiet else [])]
    result = api.train(config, arch=arch, rot_loss=rot_loss, population=population, fold=fold, seed=seed,
                       pose_frame=pose_frame, train_trajectories=train_trajectories, profile=profile,
                       overrides=set_ or (), use_tuned=use_tuned, resume=run_id or resume, again=again,
                       progress=not quiet, console=console,
                       resumed_by=lambda rid: shlex.join(["bronchopose", "train", *flags, "--resume", "--run-id", rid]))
    console.print(result.summary() if result.ok else f"[red]{result.summary()}[/]", highlight=False)
    raise typer.Exit(0 if result.ok else 1)
