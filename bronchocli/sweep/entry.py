"""``bronchopose sweep``'s modes as library calls: the command parses its flags, loads the config
(``task.TaskSpec.load``, the same call an array task makes) and calls exactly one of these.

- ``run``: the plan's stages here, with local worker processes (``staged.run_sweep``);
- ``dry_run``: the plan and each cell's state; nothing is started;
- ``gc``: remove the checkpoints no live cell needs on this machine;
- ``launch_slurm``: submit the workers as Slurm job arrays, then watch (``slurm.launch``);
- ``cancel``: scancel the sweep's Slurm jobs.

The sixth way in is not a mode of the command: a Slurm array task starts
``python -m bronchocli.sweep.task '<spec>'`` (``task.main``).
"""

from __future__ import annotations

from rich.console import Console

from ..cells import Selection
from ..config import Config
from ..runlayout import check_paths
from . import placement, slurm, staged, task
from .checkpoints import collect_garbage
from .status import fmt_bytes
from .storage import SweepStore
from .worker import Runner, default_runner


def open_store(cfg: Config) -> SweepStore:
    return SweepStore(cfg.paths.storage_url, cfg.tracking.timeout_s, cfg.tracking.busy_timeout_s)


def _local_store(cfg: Config) -> SweepStore:
    check_paths(cfg, storage=True, logs=True)  # before anything is created (a dry run says so too)
    store = open_store(cfg)
    store.exists()  # an unreachable storage fails here, in tracking.timeout_s, before anything is created
    return store


def _workers(workers: int | None, gpus: str, per_gpu: int) -> tuple[int, list[str]]:
    """Local workers and their GPUs: ``--gpus`` (auto, none or a list), default GPUs x ``per_gpu`` (else 1)."""
    devices = placement.parse_gpus(gpus, placement.visible_gpus())
    return workers or placement.default_workers(devices, per_gpu), devices


def run(cfg: Config, only: Selection, *, workers: int | None = None, gpus: str = "auto", per_gpu: int = 1,
        retry_failed: bool = False, runner: Runner = default_runner, console: Console) -> int:
    """Run every cell of the plan not FINISHED with local workers; 0 all FINISHED, 1 some FAILED, 130 stopped."""
    store = _local_store(cfg)
    n, devices = _workers(workers, gpus, per_gpu)
    if cfg.model.pretrained is not None:  # fetch/find backbone weights once, before any worker or run starts
        from ..models import initialisation  # lazy: torch loads in the sweep's parent only when weights are needed

        initialisation(cfg.paths.pretrained, sorted({a for g in [cfg.grid, *(st.stage_grid(cfg.grid)
                                                                          for st in cfg.stages)] for a in g.arch}))
    return staged.run_sweep(cfg, store, only=only, workers=n, console=console, retry_failed=retry_failed,
                            gpus=devices, runner=runner)


def dry_run(cfg: Config, only: Selection, *, workers: int | None = None, gpus: str = "auto", per_gpu: int = 1,
            console: Console) -> int:
    """Print the plan (per stage: its cells and their state) and the workers a run would start; starts nothing."""
    store = _local_store(cfg)
    n, _ = _workers(workers, gpus, per_gpu)
    staged.dry_run(cfg, store, only, n, console)
    return 0


def gc(cfg: Config, console: Console) -> int:
    """Remove the checkpoints no live cell needs on this machine and say what was freed."""
    store = open_store(cfg)
    freed = collect_garbage(cfg, store if store.exists() else None)
    for ck, n in freed:
        what = "rejected/temporary files" if ck.needed else ck.why
        console.print(f"freed {fmt_bytes(n)}: {ck.folder} ({what})", highlight=False)
    console.print(f"--gc: freed {fmt_bytes(sum(n for _, n in freed))} in {len(freed)} checkpoint folder(s)")
    return 0


def launch_slurm(cfg: Config, spec: task.TaskSpec, *, detach: bool = False, retry_failed: bool = False,
                 console: Console) -> int:
    """Submit the plan's workers as Slurm job arrays (each task: ``task.command`` with ``spec``) and, unless
    ``detach``, watch them; re-running submits only what the queued and running tasks do not cover."""
    check_paths(cfg, storage=True, logs=True)
    return slurm.launch(cfg, open_store(cfg), spec.selection(), task.command(cfg, spec), detach=detach,
                        console=console, retry_failed=retry_failed)


def cancel(cfg: Config, console: Console) -> int:
    """scancel every queued or running job of the sweep (running workers release their cells)."""
    return slurm.cancel(cfg, console)
