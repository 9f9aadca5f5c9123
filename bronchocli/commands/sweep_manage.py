"""`bronchopose sweep plan | gc | cancel`: print the plan, reclaim checkpoints, stop a sweep's workers (each a
thin layer over ``sweep.entry``)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..config import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt
from .sweep_options import GpusOpt, OnlyOpt, PerGpuOpt, StorageOpt, UseTunedOpt, WorkersOpt, task_spec, wide_console


def plan(
    workers: Optional[int] = WorkersOpt,
    gpus: Optional[str] = GpusOpt,
    per_gpu: Optional[int] = PerGpuOpt,
    storage: Optional[str] = StorageOpt,
    only: Optional[list[str]] = OnlyOpt,
    use_tuned: Optional[str] = UseTunedOpt,
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Print the plan: per stage its cells and their state, and the local workers `run` would start.

    Changes nothing anywhere: no job submitted, no file or row written.
    """
    from ..sweep import entry  # lazy: keeps `bronchopose --help` fast

    spec = task_spec(config, profile, set_, storage, use_tuned, only)
    cfg = spec.load()
    raise typer.Exit(entry.dry_run(cfg, spec.selection(), workers=workers, gpus=gpus or "auto",
                                   per_gpu=per_gpu or 1, console=wide_console()))


def gc(
    dry_run: bool = typer.Option(False, "--dry-run", help="List what would be removed; remove nothing."),
    storage: Optional[str] = StorageOpt,
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Remove the checkpoints no live cell needs on this machine (finished, orphaned, failed for good, refused
    files, tune trials no trial will resume) and print what was freed, then what is kept and why; only what a run
    provably wrote is ever removed."""
    from ..sweep import entry  # lazy: keeps `bronchopose --help` fast

    cfg = task_spec(config, profile, set_, storage).load()
    raise typer.Exit(entry.gc(cfg, wide_console(), dry_run=dry_run))


def cancel(
    launcher: Optional[str] = typer.Option(None, "--launcher", help="The launcher whose workers to stop "
                                           "(default: sweep.launcher)."),
    dry_run: bool = typer.Option(False, "--dry-run", help="List the workers that would be stopped; stop nothing."),
    study: Optional[str] = typer.Option(None, "--study", help="Stop this tuning study's workers (`tune "
                                        "--launcher`) instead of the sweep's."),
    storage: Optional[str] = StorageOpt,
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Stop this sweep's (or --study's) queued and running workers (Slurm: scancel its jobs); running cells and
    trials are released and resume from their checkpoints when the sweep (or tune) is run again."""
    from ..sweep import entry  # lazy: keeps `bronchopose --help` fast

    cfg = task_spec(config, profile, set_, storage).load()
    raise typer.Exit(entry.cancel(cfg, entry.launcher_kind(cfg, launcher), wide_console(), dry_run=dry_run,
                                  study=study))
