"""`bronchopose sweep plan | gc | cancel`: print the plan, reclaim checkpoints, stop a sweep's workers (each a
thin layer over ``bronchocli.api.manage``)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt
from .launcher_flags import given
from .sweep_options import OnlyOpt, StorageOpt, UseTunedOpt, wide_console


def plan(
    ctx: typer.Context,
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
    from ..api import manage  # lazy: keeps `bronchopose --help` fast

    raise typer.Exit(manage.plan(config, only=only or (), storage=storage, use_tuned=use_tuned, profile=profile,
                                 overrides=set_ or (), console=wide_console(), **given(ctx)))


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
    from ..api import manage  # lazy: keeps `bronchopose --help` fast

    raise typer.Exit(manage.gc(config, dry_run=dry_run, storage=storage, profile=profile, overrides=set_ or (),
                               console=wide_console()))


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
    from ..api import manage  # lazy: keeps `bronchopose --help` fast

    raise typer.Exit(manage.cancel(config, launcher=launcher, dry_run=dry_run, study=study, storage=storage,
                                   profile=profile, overrides=set_ or (), console=wide_console()))
