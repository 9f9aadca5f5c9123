"""`bronchopose sweep`: run every cell of the plan exactly once with local workers over shared storage.

Parses the flags, loads the config and calls one mode of ``sweep.entry`` (run, dry_run, gc, launch_slurm,
cancel); docs/sweep.md, "Modes".
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..cells import FIELDS
from ..config import DEFAULT_CONFIG
from ..errors import BronchoError
from .common import ConfigOpt, ProfileOpt, SetOpt
from .common import console as _console

ONLY_HELP = ("Run only matching cells: key=value[,value...], keys joined by ';' or repeated --only "
             f"({', '.join(FIELDS)}), e.g. --only 'arch=lstm,conv3d;population=personalized'.")
STORAGE_HELP = ("Claims database URL, overriding storage.url (sqlite:///runs/sweep.db; "
                "postgresql://user:${PGPASSWORD}@host/db for many machines).")


def sweep(
    workers: Optional[int] = typer.Option(None, "--workers", "-w", min=1,
                                          help="Local worker processes (torch threads = cores / N). Default: "
                                          "GPUs x --per-gpu on a GPU machine, else 1."),
    gpus: str = typer.Option("auto", "--gpus", help="GPUs for the workers, round-robin: auto (every visible "
                             "one, honouring CUDA_VISIBLE_DEVICES), none, or a list such as 0,1."),
    per_gpu: int = typer.Option(1, "--per-gpu", min=1, help="Cells run at once on each GPU (small cells leave "
                                "a GPU idle; packing several raises throughput)."),
    storage: Optional[str] = typer.Option(None, "--storage", help=STORAGE_HELP),
    only: Optional[list[str]] = typer.Option(None, "--only", help=ONLY_HELP),
    dry_run: bool = typer.Option(False, "--dry-run", help="Print the plan (cells and their state) and exit; with "
                                 "--gc: what would be removed; with --cancel: the jobs that would be cancelled. "
                                 "Changes nothing, with any other flag."),
    retry_failed: bool = typer.Option(False, "--retry-failed",
                                      help="Reset FAILED cells (and their retry budget) first."),
    gc: bool = typer.Option(False, "--gc", help="Remove the checkpoints no live cell needs (finished, orphaned, "
                            "failed for good), print what was freed, and exit."),
    use_tuned: Optional[str] = typer.Option(None, "--use-tuned",
                                            help="Apply the best trial of this Optuna study to every cell."),
    launcher: Optional[str] = typer.Option(None, "--launcher", help="local: worker processes here; slurm: "
                                           "submit Slurm job arrays of workers (slurm section, docs/cluster.md). "
                                           "Default: sweep.launcher."),
    detach: bool = typer.Option(False, "--detach", help="Slurm: return once submitted instead of watching."),
    cancel: bool = typer.Option(False, "--cancel", help="Slurm: cancel this sweep's queued and running jobs."),
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
    `bronchopose sweep` processes, on any machines, pointed at the same storage
    cooperate: each cell is claimed by one worker and yields one FINISHED MLflow run.
    Re-running resumes (FINISHED cells are skipped); FAILED cells are retried up to
    sweep.max_retries; a killed worker's cell is taken over after sweep.stale_after_s.
    With `--launcher slurm` every worker is a Slurm array task instead (docs/cluster.md):
    re-running submits only what the sweep's queued and running jobs do not cover,
    `--detach` returns at once, `--cancel` cancels the sweep's jobs.
    `--runner module:function` runs each cell with that function instead of training.
    Exit code 0 when every cell finished, 1 when some failed, 130 when interrupted.
    """
    from ..sweep import entry  # lazy: keeps `bronchopose --help` fast
    from ..sweep.status import wide
    from ..sweep.task import TaskSpec

    spec = TaskSpec(config=str(config), profile=profile, overrides=tuple(set_ or ()), storage=storage,
                    use_tuned=use_tuned, only=tuple(only or ()), runner=runner)
    cfg = spec.load()  # as every Slurm array task loads it
    selection, cell_runner = spec.selection(), spec.cell_runner()
    if launcher not in (None, "local", "slurm"):
        raise BronchoError(f"--launcher {launcher}: must be local or slurm")
    use_slurm = (launcher or cfg.sweep.launcher) == "slurm"
    if (detach or cancel) and not use_slurm:
        raise BronchoError(f"{'--detach' if detach else '--cancel'}: only with --launcher slurm "
                           "(or sweep.launcher: slurm)")
    console = wide(_console)
    if gc:
        code = entry.gc(cfg, console, dry_run=dry_run)
    elif cancel:
        code = entry.cancel(cfg, console, dry_run=dry_run)
    elif use_slurm and not dry_run:
        code = entry.launch_slurm(cfg, spec, detach=detach, retry_failed=retry_failed, console=console)
    elif dry_run:
        code = entry.dry_run(cfg, selection, workers=workers, gpus=gpus, per_gpu=per_gpu, console=console)
    else:
        code = entry.run(cfg, selection, workers=workers, gpus=gpus, per_gpu=per_gpu, retry_failed=retry_failed,
                         runner=cell_runner, console=console)
    raise typer.Exit(code)
