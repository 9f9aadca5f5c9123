"""`bronchopose sweep run`: the config's plan, each cell once, with a launcher (``bronchocli.api.sweep``); the
launchers' options (``--workers``, a plugin's own) are added by ``launcher_flags`` (``commands/sweep.py``)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt
from .launcher_flags import given
from .sweep_options import OnlyOpt, StorageOpt, UseTunedOpt, wide_console


def run(
    ctx: typer.Context,
    storage: Optional[str] = StorageOpt,
    only: Optional[list[str]] = OnlyOpt,
    retry_failed: bool = typer.Option(False, "--retry-failed",
                                      help="Reset FAILED cells (and their retry budget) first."),
    use_tuned: Optional[str] = UseTunedOpt,
    launcher: Optional[str] = typer.Option(None, "--launcher", help="Where the workers run: local (processes "
                                           "here), slurm (Slurm job arrays; sweep.launchers.slurm, docs/cluster.md), "
                                           "or another known launcher. Default: sweep.launcher."),
    detach: bool = typer.Option(False, "--detach", help="A launcher whose workers outlive this command (slurm): "
                                "return once submitted instead of watching."),
    runner: Optional[str] = typer.Option(None, "--runner", help="Run each cell with this function instead of "
                                         "training: module:function with run_cell's signature, importable by the "
                                         "workers (e.g. on PYTHONPATH); docs/sweep.md, \"Cell runners\"."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Run the config's plan, each cell once: its grid, or its stages in order (the paper's protocol).

    Prints the plan, generates the dataset if missing, then runs every cell that is
    not FINISHED with N local worker processes and shows live progress. A stage that
    selects from an earlier one (top-k combinations by a validation metric) starts
    once that stage is done; the selection is recorded and printed. Any number of
    `bronchopose sweep run` processes, on any machines, pointed at the same storage
    cooperate: each cell is claimed by one worker and yields one FINISHED MLflow run.
    Re-running resumes (FINISHED cells are skipped); FAILED cells are retried up to
    sweep.max_retries; a killed worker's cell is taken over after sweep.stale_after_s.
    With `--launcher slurm` every worker is a Slurm array task instead (docs/cluster.md):
    re-running submits only what the sweep's queued and running jobs do not cover,
    `--detach` returns at once (`bronchopose sweep cancel` stops the jobs).
    Exit code 0 when every cell finished, 1 when some failed, 130 when interrupted.
    """
    from .. import api  # lazy: keeps `bronchopose --help` fast

    result = api.sweep(config, only=only or (), launcher=launcher, retry_failed=retry_failed, detach=detach,
                       storage=storage, use_tuned=use_tuned, runner=runner, profile=profile, overrides=set_ or (),
                       console=wide_console(), **given(ctx))
    raise typer.Exit(result.exit_code)
