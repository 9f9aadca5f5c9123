"""`bronchopose train`: train and evaluate one grid cell as one MLflow run."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..config import ARCHS, DEFAULT_CONFIG, POPULATIONS, POSE_FRAMES, ROT_LOSSES, make_cell
from ..errors import BronchoError
from .common import ConfigOpt, ProfileOpt, SetOpt, console, load


def _choice(value: str, allowed: tuple[str, ...], flag: str) -> str:
    if value not in allowed:
        raise BronchoError(f"{flag} {value!r}: must be one of {', '.join(allowed)}")
    return value


def train(
    arch: str = typer.Option(..., "--arch", "-a", help=f"Architecture: {', '.join(ARCHS)}."),
    rot_loss: str = typer.Option(..., "--rot-loss", "-l", help=f"Rotation loss: {', '.join(ROT_LOSSES)}."),
    population: str = typer.Option(..., "--population", "-P", help=f"Population: {', '.join(POPULATIONS)}."),
    fold: Optional[str] = typer.Option(None, "--fold", help="Held-out patient (cross-subject only)."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the run."),
    pose_frame: str = typer.Option("world", "--pose-frame", help=f"Relative-pose frame: {', '.join(POSE_FRAMES)}."),
    resume: bool = typer.Option(False, "--resume", help="Continue this cell's latest KILLED/FAILED run from its checkpoint."),
    run_id: Optional[str] = typer.Option(None, "--run-id", help="With --resume: the MLflow run to continue."),
    use_tuned: Optional[str] = typer.Option(None, "--use-tuned", help="Apply the best trial of this Optuna study."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Train one (arch, rot_loss, population, fold, seed, pose_frame) cell and evaluate it on its test split.

    Generates the configured dataset first if it does not exist. Progress is shown
    per epoch; the run, its metrics (per pair and accumulated), the resolved config,
    split manifest, predictions CSV, trajectory plot and best checkpoint land in
    MLflow (`bronchopose ui`). Ctrl-C stops at the next batch, saves a checkpoint
    and marks the run KILLED; `--resume` continues it. Exit code 1 when the run FAILED.
    """
    from ..training.run import run_cell

    cfg = load(config, profile, set_)
    _choice(arch, ARCHS, "--arch")
    _choice(rot_loss, ROT_LOSSES, "--rot-loss")
    _choice(population, POPULATIONS, "--population")
    _choice(pose_frame, POSE_FRAMES, "--pose-frame")
    if population == "cross-subject" and fold is None:
        raise BronchoError("--fold: cross-subject needs the held-out patient (e.g. --fold p00)")
    if population == "personalized" and fold is not None:
        raise BronchoError("--fold: only cross-subject runs have a held-out patient")
    if run_id and not resume:
        raise BronchoError("--run-id: only meaningful with --resume")
    if use_tuned:
        from ..tuning import apply_best

        cfg = apply_best(cfg, use_tuned)
        console.print(f"hyperparameters from {cfg.tune.applied}")
    cell = make_cell(cfg, arch, rot_loss, population, fold, seed, pose_frame)
    console.print(f"[bold]train[/] {cell.label}  (cell {cell.key}, experiment {cfg.experiment_name})")
    result = run_cell(cfg, cell, resume=run_id or resume, progress=not quiet)
    if result.status != "FINISHED":
        console.print(f"[red]run {result.run_id} {result.status}:[/] {result.failure_reason}")
        raise typer.Exit(1)
    m = result.metrics
    if result.stop_requested:
        console.print("[yellow]interrupt received during evaluation: the run was completed first[/]")
    console.print(
        f"run {result.run_id} FINISHED in {result.duration_s:.1f} s — "
        f"pair pos L2 {m['pair.pos_l2.mean']:.3f} vox, pair CE {m['pair.ce.mean']:.4f}, "
        f"accumulated pos L2 {m['acc.pos_l2.mean']:.2f} vox"
    )
