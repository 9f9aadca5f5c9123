"""`bronchopose sweep run | plan | status | gc | cancel`: a sweep's verbs, each with only its own options.

``bronchopose sweep`` with no verb (or with run's options only) is ``sweep run``. The modes that were flags
(``--gc``, ``--cancel``, ``--dry-run``) are verbs; given as flags they are refused in one line, exit 2. Each verb
parses its flags, loads the config and calls one library call of ``sweep.entry``; docs/sweep.md, "Verbs".
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer
from typer._click import Context  # Typer 0.29 vendors click (pyproject pins typer < 0.30)
from typer._click.exceptions import UsageError
from typer.core import TyperGroup

from ..cells import FIELDS
from ..config import DEFAULT_CONFIG
from ..config.sections import MAX_WORKERS
from ..errors import BronchoError
from . import status as status_cmd
from .common import ConfigOpt, ProfileOpt, SetOpt
from .common import console as _console

ONLY_HELP = ("Run only matching cells: key=value[,value...], keys joined by ';' or repeated --only "
             f"({', '.join(FIELDS)}), e.g. --only 'arch=lstm,conv3d;population=personalized'.")
STORAGE_HELP = ("Claims database URL, overriding storage.url (sqlite:///runs/sweep.db; "
                "postgresql://user:${PGPASSWORD}@host/db for many machines).")
DEFAULT_VERB = "run"
# The modes that were flags of `bronchopose sweep`, and the verb each is now.
OLD_FLAGS = {"--gc": "gc", "--cancel": "cancel", "--dry-run": "plan"}


class SweepGroup(TyperGroup):
    """A group whose default verb is ``run``: ``sweep [run's options]`` is ``sweep run [...]``."""

    def parse_args(self, ctx: Context, args: list[str]) -> list[str]:
        if not args or (args[0] not in self.commands and args[0] not in ctx.help_option_names):
            args = [DEFAULT_VERB, *args]
        old = [a for a in args if a.split("=", 1)[0] in OLD_FLAGS] if args[0] == DEFAULT_VERB else []
        if old:
            verbs = ", ".join(f"{a} is `bronchopose sweep {OLD_FLAGS[a.split('=', 1)[0]]}`" for a in old)
            raise UsageError(f"{' '.join(old)}: the sweep's modes are verbs, one at a time: {verbs}", ctx)
        return super().parse_args(ctx, args)


app = typer.Typer(cls=SweepGroup, no_args_is_help=False,
                  help="Run a sweep's plan exactly once per cell and manage it: run (the default), plan, status, "
                  "gc, cancel.")


def _spec(config: Path, profile: str | None, set_: list[str] | None, storage: str | None,
          use_tuned: str | None = None, only: list[str] | None = None, runner: str | None = None) -> Any:
    from ..sweep.task import TaskSpec  # lazy: keeps `bronchopose --help` fast

    return TaskSpec(config=str(config), profile=profile, overrides=tuple(set_ or ()), storage=storage,
                    use_tuned=use_tuned, only=tuple(only or ()), runner=runner)


def _wide() -> Any:
    from ..sweep.status import wide  # lazy: keeps `bronchopose --help` fast

    return wide(_console)


WorkersOpt = typer.Option(None, "--workers", "-w", min=1, max=MAX_WORKERS, help="Local worker processes (torch "
                          "threads = cores / N), one per cell left at most. Default: GPUs x --per-gpu on a GPU "
                          "machine, else 1.")
GpusOpt = typer.Option(None, "--gpus", help="GPUs for the local workers, round-robin: auto (every visible one, "
                       "honouring CUDA_VISIBLE_DEVICES; the default), none, or a list such as 0,1.")
PerGpuOpt = typer.Option(None, "--per-gpu", min=1, help="Cells run at once on each GPU (default 1; small cells "
                         "leave a GPU idle, packing several raises throughput).")
StorageOpt = typer.Option(None, "--storage", help=STORAGE_HELP)
OnlyOpt = typer.Option(None, "--only", help=ONLY_HELP)
UseTunedOpt = typer.Option(None, "--use-tuned", help="Apply the best trial of this Optuna study to every cell.")


@app.command(name="run")
def run(
    workers: Optional[int] = WorkersOpt,
    gpus: Optional[str] = GpusOpt,
    per_gpu: Optional[int] = PerGpuOpt,
    storage: Optional[str] = StorageOpt,
    only: Optional[list[str]] = OnlyOpt,
    retry_failed: bool = typer.Option(False, "--retry-failed",
                                      help="Reset FAILED cells (and their retry budget) first."),
    use_tuned: Optional[str] = UseTunedOpt,
    launcher: Optional[str] = typer.Option(None, "--launcher", help="Where the workers run: local (processes "
                                           "here), slurm (Slurm job arrays; slurm section, docs/cluster.md), or "
                                           "another registered launcher. Default: sweep.launcher."),
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
    from ..sweep import entry  # lazy: keeps `bronchopose --help` fast

    spec = _spec(config, profile, set_, storage, use_tuned, only, runner)
    cfg = spec.load()  # as every Slurm array task loads it
    spec.selection()  # a bad --only or --runner: one line before anything else
    spec.cell_runner()
    kind = entry.launcher_kind(cfg, launcher)
    options = entry.launcher_options(kind, {"--workers": workers, "--gpus": gpus, "--per-gpu": per_gpu})
    if detach and not kind.detachable:
        raise BronchoError(f"--detach: launcher {kind.name} runs its workers in this command; only a launcher "
                           "whose workers outlive it (slurm) can detach")
    raise typer.Exit(entry.run(cfg, spec, kind, options=options, detach=detach, retry_failed=retry_failed,
                               console=_wide()))


@app.command(name="plan")
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

    spec = _spec(config, profile, set_, storage, use_tuned, only)
    cfg = spec.load()
    raise typer.Exit(entry.dry_run(cfg, spec.selection(), workers=workers, gpus=gpus or "auto",
                                   per_gpu=per_gpu or 1, console=_wide()))


@app.command(name="gc")
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

    cfg = _spec(config, profile, set_, storage).load()
    raise typer.Exit(entry.gc(cfg, _wide(), dry_run=dry_run))


@app.command(name="cancel")
def cancel(
    launcher: Optional[str] = typer.Option(None, "--launcher", help="The launcher whose workers to stop "
                                           "(default: sweep.launcher)."),
    dry_run: bool = typer.Option(False, "--dry-run", help="List the workers that would be stopped; stop nothing."),
    storage: Optional[str] = StorageOpt,
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Stop this sweep's queued and running workers (Slurm: scancel its jobs); running cells are released and
    resume from their checkpoints when the sweep is run again."""
    from ..sweep import entry  # lazy: keeps `bronchopose --help` fast

    cfg = _spec(config, profile, set_, storage).load()
    raise typer.Exit(entry.cancel(cfg, entry.launcher_kind(cfg, launcher), _wide(), dry_run=dry_run))


app.command(name="status")(status_cmd.status)  # the same command as `bronchopose status`
