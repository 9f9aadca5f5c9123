"""`bronchopose tune`: Optuna hyperparameter search for one cell, or --show a study's results."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from .. import urls
from ..cells import Arch, Population, PoseFrame, RotLoss
from ..config import DEFAULT_CONFIG, check_paths
from ..errors import BronchoError
from .common import ConfigOpt, ProfileOpt, SetOpt, ShowFormat, console, load


def _show(cfg, study: str, fmt: str) -> None:
    from ..sweep.tuning import summary  # lazy: optuna only when the command runs

    info = summary(cfg, study)
    if fmt == "json":
        console.print_json(json.dumps(info, default=str))
        return
    counts = ", ".join(f"{v} {k}" for k, v in info["counts"].items() if v)
    console.print(f"[bold]study[/] {study}: {counts or 'no trials'}")
    best = info["best"]
    if best is None:
        console.print("no completed trial yet")
        return
    table = Table("parameter", "best value", "importance", title=f"best trial #{best['number']}: "
                  f"val_loss {best['value']:.5g} (MLflow run {best['run_id']})")
    for name, value in best["params"].items():
        imp = info["importances"].get(name)
        table.add_row(name, f"{value:.4g}" if isinstance(value, float) else str(value),
                      "—" if imp is None else f"{imp:.3f}")
    console.print(table)
    if info.get("importances_note"):
        console.print(f"importances unavailable: {info['importances_note']}")
    console.print(f"apply it: bronchopose sweep --use-tuned {study}  (or train --use-tuned {study})")


def tune(
    arch: Optional[Arch] = typer.Option(None, "--arch", "-a", help="Architecture."),
    rot_loss: Optional[RotLoss] = typer.Option(None, "--rot-loss", "-l", help="Rotation loss."),
    population: Optional[Population] = typer.Option(None, "--population", "-P", help="Population."),
    fold: Optional[str] = typer.Option(None, "--fold", help="Held-out patient (cross-subject only)."),
    seed: int = typer.Option(0, "--seed", help="Training seed of every trial."),
    pose_frame: Optional[PoseFrame] = typer.Option(None, "--pose-frame", help="Relative-pose frame (default: the "
                                                   "first of the config's grid.pose_frame)."),
    train_trajectories: Optional[int] = typer.Option(None, "--train-trajectories",
                                                     help="Training trajectories per patient and lobe."),
    trials: Optional[int] = typer.Option(None, "--trials", "-n", min=1,
                                         help="Total finished trials of the study (default: tune.trials)."),
    timeout: Optional[float] = typer.Option(None, "--timeout", min=0.001,
                                            help="Stop starting trials after this many seconds."),
    storage: Optional[str] = typer.Option(None, "--storage", help="Study storage URL (default: storage.url)."),
    study: Optional[str] = typer.Option(None, "--study", help="Study name [<config name>-<arch>-<loss>-...]."),
    workers: int = typer.Option(1, "--workers", "-w", min=1, help="Local worker processes tuning the study."),
    show: bool = typer.Option(False, "--show", help="Print the best trial and parameter importances, then exit."),
    fmt: ShowFormat = typer.Option("table", "--format", help="--show output."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Tune one cell's hyperparameters over `tune.space` with Optuna (TPE, seeded), minimising validation loss.

    Every trial is an MLflow run (tags run_kind=trial, study, trial); the pruner
    (`tune.pruner`: median or hyperband) stops poor trials from their validation loss
    (every train.val_every steps). The study lives in the shared storage, so several processes
    or machines can tune it together and an interrupted study resumes. With
    --show, print the best trial and parameter importances (no training).
    """
    from ..sweep import tuning  # lazy: optuna only when the command runs

    cfg = load(config, profile, set_)
    if storage:
        cfg = cfg.with_values({"storage.url": storage})
    if fmt not in ("table", "json"):
        raise BronchoError(f"--format {fmt!r}: must be table or json")
    target = None
    if arch is not None or rot_loss is not None or population is not None:
        if arch is None or rot_loss is None or population is None:
            raise BronchoError("tune needs all of --arch, --rot-loss and --population (or --show --study NAME)")
        target = cfg.cell(arch=arch, rot_loss=rot_loss, population=population, fold=fold, seed=seed,
                          pose_frame=pose_frame, train_trajectories=train_trajectories)
    if show:
        if study is None and target is None:
            names = tuning.list_studies(cfg)
            raise BronchoError("--show needs --study NAME (or the cell's --arch/--rot-loss/--population); "
                               f"studies in the storage: {', '.join(names) or 'none'}")
        _show(cfg, study or tuning.study_name(cfg, target), fmt)
        return
    if target is None:
        raise BronchoError("tune needs --arch, --rot-loss and --population (or --show)")
    from ..generation import ensure_dataset  # lazy: keeps `bronchopose --help` fast

    check_paths(cfg, storage=True)  # one line before anything is created
    ensure_dataset(cfg)
    if cfg.model.pretrained is not None:  # missing backbone weights: one line before any study or trial run
        from ..models import initialisation  # lazy: torch only when backbone weights must be found or fetched

        initialisation(cfg.paths.pretrained, [target.arch])
    n = trials or cfg.tune.trials
    name = study or tuning.study_name(cfg, target)
    console.print(f"[bold]tune[/] {name}: {n} trials, {workers} worker(s), storage {urls.redact(cfg.paths.storage_url)}")
    s = tuning.tune(cfg, target, n, study=study, timeout=timeout or cfg.tune.timeout, workers=workers,
                    progress=not quiet)
    console.print(f"{tuning.finished(s)} finished trials in study {name}")
    _show(cfg, name, "table")
