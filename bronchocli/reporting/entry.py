"""``bronchopose report`` as a library call: collect the config's runs once, build the chosen tables (and figures),
write them, print them and their warnings.

The command checks its flags first (table names, evaluations, formats, ``--best``/``--trajectories``, the output
folder, a ``--latency-from`` file: one line each, before minutes of work), loads the config and calls ``report``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from ..config import Config
from ..errors import BronchoError
from ..sweep.storage import SweepStore
from . import report as rep
from . import tables as tbl
from .context import Profiler
from .curves import history_loader
from .figures import errors_loader, mlflow_loader
from .markdown import to_rich
from .scope import profile_plans


def report(cfg: Config, names: Sequence[str], evaluations: Sequence[str], suffixes: Sequence[str], out: Path, *,
           sweep: str | None = None, pose_frame: str | None = None, include_other_configs: bool = False,
           best: int = 0, figures: bool = True, trajectories: int = 4, profiles: Profiler | None = None,
           latency: bool = True, latency_device: str = "cpu", image_size: int | None = None, quiet: bool = False,
           to_parent: bool = True, console: Console, err_console: Console) -> rep.ReportResult:
    """Write the tables ``names`` (and, with ``figures``, the figures) of the config's runs (or of stored sweep
    ``sweep``) to ``out``. The ablation table's latency/GMAC come from ``profiles`` (``--latency-from``), else
    are measured (``latency``) at ``image_size`` on ``latency_device``, else stay empty. With ``to_parent``
    the written files are also logged to the sweep's parent MLflow run (``report/`` artifacts). Returns what was
    built and written (tables, files, warnings)."""
    client = rep.open_store(cfg)
    refuse_while_running(cfg, sweep or cfg.name)
    index = rep.collect_index(client, cfg, sweep, pose_frame, include_other_configs)
    console.print(rep.summary_index(index))
    ctx = tbl.ReportContext(index, best=best, errors=errors_loader(client), history=history_loader(client),
                            profile_plans=(lambda: profile_plans(cfg)) if sweep is None else None,
                            default_train_trajectories=None if sweep else cfg.splits.train,
                            image_size=None if sweep else rep.default_image_size(cfg))
    if profiles is not None:
        ctx.profiler = profiles
    elif latency:
        size = image_size or rep.default_image_size(cfg)
        measure = rep.measuring_profiler(size, latency_device, rep.latency_record(cfg, size, latency_device))

        def profiled(arch: str):
            with err_console.status(f"ablation latency of {arch} (recorded, else measured once) ..."):
                return measure(arch)
        ctx.profiler = profiled
    else:
        ctx.profiler_note = "--no-latency"
    warnings: list[str] = []
    started = time.perf_counter()

    def progress(text: str) -> None:
        err_console.print(f"[{time.perf_counter() - started:.1f} s] {text}", highlight=False)
    try:
        result = rep.make_report(
            ctx, names, evaluations, suffixes, out, loader=mlflow_loader(client, warnings) if figures else None,
            n_trajectories=trajectories, dataset_root=cfg.paths.dataset if figures else None, warnings=warnings,
            progress=None if quiet else progress,
        )
    except OSError as exc:  # e.g. the disk filled up: each file is written atomically, none is left half-written
        raise BronchoError(f"--out {out}: cannot write {exc.filename or 'the report'} ({exc.strerror or exc})"
                           ) from None
    if not quiet:
        for t in result.tables:
            console.print(to_rich(t))
    for w in dict.fromkeys([w for t in result.tables for w in t.warnings] + result.warnings):
        err_console.print(f"[yellow]warning:[/] {w}", highlight=False, soft_wrap=True)
    console.print(f"wrote {len(result.files)} file(s) to {out}/: " + ", ".join(p.name for p in result.files))
    if to_parent and result.files:
        console.print(rep.log_to_parent(client, cfg, index.sweep, out, result.files), highlight=False)
    return result


def refuse_while_running(cfg: Config, sweep: str) -> None:
    """One line, before any work, when cells of ``sweep`` still run (a live worker's claim): their rows would be
    rows of —. A claims storage that cannot be asked (none, unreachable) refuses nothing."""
    try:
        store = SweepStore(cfg.paths.storage_url, cfg.runs.timeout_s, cfg.runs.busy_timeout_s)
        try:
            running = store.running(sweep, cfg.sweep.stale_after_s)
        finally:
            store.close()
    except BronchoError:
        return
    if running:
        shown = ", ".join(r.label for r in running[:3]) + (", ..." if len(running) > 3 else "")
        raise BronchoError(f"report: sweep {sweep} has {len(running)} cell(s) still running ({shown}); their rows "
                           "would be empty (—): run the report when `bronchopose status` shows them done")
