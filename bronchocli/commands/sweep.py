"""`bronchopose sweep`: run every cell of the plan exactly once with local workers over shared storage."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..cells import FIELDS, parse_only
from ..config import DEFAULT_CONFIG, check_paths
from ..errors import BronchoError
from .common import ConfigOpt, ProfileOpt, SetOpt, load
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
    dry_run: bool = typer.Option(False, "--dry-run", help="Print the plan (cells and their state) and exit."),
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
    worker_only: bool = typer.Option(False, "--worker-only", hidden=True,
                                     help="Internal: run one worker through the stages (a Slurm array task)."),
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
    Exit code 0 when every cell finished, 1 when some failed, 130 when interrupted.
    """
    from ..sweep import SweepStore, placement, staged  # lazy: keeps `bronchopose --help` fast
    from ..sweep.status import wide

    console = wide(_console)
    cfg = load(config, profile, set_)
    selection = parse_only(only)
    if storage:
        cfg = cfg.with_values({"storage.url": storage})
    if use_tuned:  # new values -> new cell keys: tuned cells never reuse untuned runs
        from ..sweep.tuning import apply_best  # lazy: optuna only with --use-tuned

        cfg = apply_best(cfg, use_tuned)
    if launcher not in (None, "local", "slurm"):
        raise BronchoError(f"--launcher {launcher}: must be local or slurm")
    use_slurm = (launcher or cfg.sweep.launcher) == "slurm"
    if (detach or cancel) and not use_slurm:
        raise BronchoError(f"{'--detach' if detach else '--cancel'}: only with --launcher slurm "
                           "(or sweep.launcher: slurm)")
    if gc:
        store = SweepStore(cfg.paths.storage_url, cfg.runs.timeout_s, cfg.runs.busy_timeout_s)
        raise typer.Exit(_collect_garbage(cfg, store, console))
    if not cancel:
        check_paths(cfg, storage=True, logs=True)  # before anything is created (a dry run says so too)
    store = SweepStore(cfg.paths.storage_url, cfg.runs.timeout_s, cfg.runs.busy_timeout_s)
    if worker_only:
        from ..sweep import slurm  # lazy: only array tasks need it

        raise typer.Exit(slurm.worker_main(cfg, store, selection))
    if use_slurm and cancel:
        from ..sweep import slurm  # lazy: only the Slurm launcher needs it

        raise typer.Exit(slurm.cancel(cfg, console))
    if use_slurm and not dry_run:
        from ..sweep import slurm  # lazy: only the Slurm launcher needs it

        slurm.check(cfg)  # before touching storage: one line, nothing created, nothing submitted
        store.exists()
        argv = _worker_argv(config, profile, set_, storage, only, use_tuned)
        raise typer.Exit(slurm.launch(cfg, store, selection, argv, detach=detach, console=console,
                                      retry_failed=retry_failed))
    store.exists()  # an unreachable storage fails here, in runs.timeout_s, before anything is created
    devices = placement.parse_gpus(gpus, placement.visible_gpus())
    workers = workers or placement.default_workers(devices, per_gpu)
    if dry_run:
        staged.dry_run(cfg, store, selection, workers, console)
        return
    if cfg.model.pretrained is not None:  # fetch/find backbone weights once, before any worker or run starts
        from ..models import initialisation  # lazy: torch loads in the sweep's parent only when weights are needed

        initialisation(cfg.paths.pretrained, sorted({a for g in [cfg.grid, *(st.stage_grid(cfg.grid)
                                                                          for st in cfg.stages)] for a in g.arch}))
    raise typer.Exit(staged.run_sweep(cfg, store, only=selection, workers=workers, console=console,
                                      retry_failed=retry_failed, gpus=devices))


def _worker_argv(config: Path, profile: Optional[str], set_: Optional[list[str]], storage: Optional[str],
                 only: Optional[list[str]], use_tuned: Optional[str]) -> list[str]:
    """The options an array task's worker needs to load the same config, storage and selection."""
    argv = ["--config", str(config.resolve())]
    if profile:
        argv += ["--profile", profile]
    for text in set_ or []:
        argv += ["--set", text]
    if storage:
        argv += ["--storage", storage]
    for text in only or []:
        argv += ["--only", text]
    if use_tuned:
        argv += ["--use-tuned", use_tuned]
    return argv


def _collect_garbage(cfg, store, console) -> int:
    """`--gc`: remove the checkpoints no live cell needs on this machine and say what was freed."""
    from ..sweep.housekeeping import collect_garbage  # lazy: keeps `bronchopose --help` fast
    from ..sweep.status import fmt_bytes

    freed = collect_garbage(cfg, store if store.exists() else None)
    for ck, n in freed:
        what = "rejected/temporary files" if ck.needed else ck.why
        console.print(f"freed {fmt_bytes(n)}: {ck.folder} ({what})", highlight=False)
    console.print(f"--gc: freed {fmt_bytes(sum(n for _, n in freed))} in {len(freed)} checkpoint folder(s)")
    return 0
