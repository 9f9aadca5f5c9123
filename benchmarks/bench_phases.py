"""Where the main job's time goes (issue 39, item 2): each phase in seconds and as a share of the whole, and the
share that is not training (goal: <= 10 %).

    python benchmarks/bench_phases.py [--set KEY=VALUE ...] [--install-s S] [--keep DIR]   # runs the main job
    python benchmarks/bench_phases.py --project DIR [--set KEY=VALUE ...] [--install-s S]  # reads a finished one

Without ``--project`` it runs the main job's commands in a temporary project (the repository's
``experiments.yaml``, its ``--set`` overrides, a claims folder of its own), each timed from process start to
exit: ``bronchopose data generate``, ``bronchopose sweep run --workers 2`` (the README's ``sweep --workers 2``
generates the dataset itself: here it is timed apart), ``bronchopose report --table all`` (its first run:
ablation latency timed, figures drawn). With ``--project DIR`` it reads a project whose sweep has run (the
README's main job from a clone, say): the sweep's wall time is then its parent run's start to end, the
dataset's the span of the dataset folder's file times, and the report is not timed.

The install is measured apart (benchmarks/README.md: a fresh venv, ``pip install`` against ``uv pip install``)
and joins the whole with ``--install-s``.

Per cell, from what the runs log:

* **start → first step**: claim (claims table) → MLflow run start (data preparation, run creation) + the
  engine's ``train.first_step_s`` (model, first step) − one average step (that step is training time);
* **training** ``train.time_s``, **validation + BatchNorm re-estimation** ``train.val_time_s``, the
  **checkpoints** written at validations ``train.checkpoint_time_s`` (runs before issue 39 do not log it: then
  in "other"), **test evaluation** ``eval.time_s``;
* **model logging**: the worker log's "logging metrics, predictions ..." line → the run's end (metrics,
  artifacts, the MLflow Model); without the log: the rest of the cell;
* **other in the cell**: the cell's claim → finish minus the above (the run's start-of-run logging, system
  metrics, checkpoint removal, recording the claim).

Per worker: **worker start** (process start → first claim; the process start from the first cell's
``train.process_first_step_s``), and the lanes' rest, **sweep start, end and idle workers** (the parent's
planning, the last cell running alone, exits). Cell phases are summed over the cells and divided by the
workers: wall-equivalent seconds, which add up to the sweep's wall time.
"""

from __future__ import annotations

import argparse
import datetime as dt
import re
import shutil
import tempfile
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench_common import cell_runs, claim_rows, cpu_line, parent_runs, private_env, project_config, timed

REPO = Path(__file__).resolve().parents[1]
LOG_LINE = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) \S+ INFO bronchocli\.training\.run: (.+?): "
                      r"logging metrics")
CELL_PHASES = ("start → first step", "training", "validation + BN re-estimation", "checkpoints",
               "test evaluation", "model logging", "other in the cell")


@dataclass
class MainJob:
    """A project and the wall seconds of the commands that were timed (None: not timed)."""

    folder: Path
    overrides: list[str]
    dataset_s: float | None = None
    sweep_s: float | None = None
    report_s: float | None = None
    workers: int = 2
    notes: list[str] = field(default_factory=list)


def new_project(root: Path, name: str, overrides: Sequence[str] = ()) -> Path:
    """A project folder with the repository's experiments.yaml."""
    folder = root / name
    folder.mkdir(parents=True)
    shutil.copy(REPO / "experiments.yaml", folder / "experiments.yaml")
    return folder


def set_args(overrides: Sequence[str]) -> list[str]:
    return [a for kv in overrides for a in ("--set", kv)]


def run_main_job(root: Path, overrides: Sequence[str], *, workers: int = 2, report: bool = True,
                 folder: Path | None = None) -> MainJob:
    """The main job's commands in ``folder`` (default: a new project ``root/main``), each timed."""
    folder = folder or new_project(root, "main")
    env, sets = private_env(root), set_args(overrides)
    job = MainJob(folder, list(overrides), workers=workers)
    job.dataset_s = timed(folder, env, "data", "generate", *sets, log="generate.log")
    print(f"# dataset generated: {job.dataset_s:.1f} s", flush=True)
    job.sweep_s = timed(folder, env, "sweep", "run", "--workers", str(workers), *sets, log="sweep.log")
    print(f"# sweep --workers {workers}: {job.sweep_s:.1f} s", flush=True)
    if report:
        job.report_s = timed(folder, env, "report", "--table", "all", *sets, log="report.log")
        print(f"# report --table all (first run): {job.report_s:.1f} s", flush=True)
    return job


def read_project(folder: Path, overrides: Sequence[str], workers: int) -> MainJob:
    """A finished project: the sweep's wall from its parent run, the dataset's from its files' times."""
    job = MainJob(folder, list(overrides), workers=workers)
    parents = [r for r in parent_runs(folder, overrides) if r.info.end_time]
    if parents:
        job.sweep_s = sum((r.info.end_time - r.info.start_time) / 1000 for r in parents)
        job.notes.append("sweep: its parent run's start → end (the command's interpreter start not included)")
    root = project_config(folder, overrides).paths.dataset
    times = [p.stat().st_mtime for p in root.rglob("*") if p.is_file()] if root.is_dir() else []
    if times:
        job.dataset_s = max(times) - min(times)
        job.notes.append("dataset: first → last file written in dataset.root (start-up before the first frame "
                         "not included)")
    return job


def logging_starts(log_dir: Path) -> dict[str, list[float]]:
    """Per cell label, the epoch seconds of its "logging metrics" lines in the sweep's worker logs."""
    out: dict[str, list[float]] = defaultdict(list)
    for log in sorted(log_dir.rglob("*.log")) if log_dir.is_dir() else []:
        for line in log.read_text(errors="replace").splitlines():
            m = LOG_LINE.match(line)
            if m:
                stamp = dt.datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()  # local time, as logged
                out[m.group(2)].append(stamp)
    return out


def cell_phases(run: Any, row: Any, logged: dict[str, list[float]]) -> dict[str, float]:
    """The phases of one cell (seconds; see the module doc)."""
    m, info = run.data.metrics, run.info
    start, end = info.start_time / 1000, info.end_time / 1000
    step_s = m["train.time_s"] / max(m.get("train.steps", 1.0), 1.0)
    out = {"start → first step": start - row.claimed_at + m.get("train.first_step_s", 0.0) - step_s,
           "training": m["train.time_s"], "validation + BN re-estimation": m["train.val_time_s"],
           "checkpoints": m.get("train.checkpoint_time_s", 0.0), "test evaluation": m.get("eval.time_s", 0.0)}
    marks = [t for t in logged.get(row.label, []) if row.claimed_at <= t <= end]
    cell_s = row.finished_at - row.claimed_at
    rest = cell_s - sum(out.values())
    out["model logging"] = end - marks[-1] if marks else rest
    out["other in the cell"] = rest - out["model logging"]
    out["cell"] = cell_s
    return out


def worker_start(runs: list[tuple[Any, Any]]) -> float | None:
    """Process start → first claim of one worker, from its first cell's run (None when not logged)."""
    run, row = min(runs, key=lambda rr: rr[1].claimed_at)
    m = run.data.metrics
    if "train.process_first_step_s" not in m:
        return None
    process_start = run.info.start_time / 1000 + m.get("train.first_step_s", 0.0) - m["train.process_first_step_s"]
    return row.claimed_at - process_start


def collect(job: MainJob) -> tuple[list[tuple[str, str, dict[str, float], float]], dict[str, float]]:
    """Per cell (label, worker, phases, pairs/s) and the wall-equivalent seconds of every phase of the sweep."""
    runs = {r.info.run_id: r for r in cell_runs(job.folder, job.overrides)}
    rows = [row for row in claim_rows(job.folder, job.overrides) if row.run_id in runs and row.finished_at]
    logged = logging_starts(project_config(job.folder, job.overrides).paths.sweep_logs)
    cells, lanes = [], defaultdict(list)
    for row in sorted(rows, key=lambda r: r.claimed_at):
        run = runs[row.run_id]
        rate = run.data.metrics["train.pairs_per_s"]
        cells.append((row.label, row.worker or "?", cell_phases(run, row, logged), rate))
        lanes[row.worker].append((run, row))
    workers = max(job.workers, len(lanes))
    totals = {name: sum(c[2][name] for c in cells) / workers for name in CELL_PHASES}
    starts = [s for s in (worker_start(v) for v in lanes.values()) if s is not None]
    totals["worker start (process → first claim)"] = sum(starts) / workers
    if job.sweep_s is not None:
        busy = sum(c[2]["cell"] for c in cells) / workers + totals["worker start (process → first claim)"]
        totals["sweep start, end and idle workers"] = job.sweep_s - busy
    return cells, totals


def fmt(x: float | None, spec: str = ".1f") -> str:
    return "—" if x is None else format(x, spec)


def print_phases(job: MainJob, install_s: float | None = None) -> float | None:
    """Print the per-cell table and the phase table; returns the non-training share (None: whole unknown)."""
    cells, sweep = collect(job)
    print("\n| cell | worker | start → first step s | training s | validation + BN s | checkpoints s | "
          "test evaluation s | model logging s | other s | cell s | pairs/s (training) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for label, worker, p, rate in cells:
        print(f"| {label} | {worker} | " + " | ".join(fmt(p[k]) for k in (*CELL_PHASES, "cell")) + f" | {rate:.1f} |")
    phases: list[tuple[str, float | None]] = [("install (measured apart)", install_s), ("dataset", job.dataset_s)]
    phases += [(f"sweep: {k}", v) for k, v in sweep.items()]
    phases.append(("report --table all (first run)", job.report_s))
    known = [v for _, v in phases if v is not None]
    whole = sum(known)
    print(f"\nThe main job's phases ({job.workers} workers: a cell phase = its sum over the cells ÷ the workers, "
          "wall-equivalent seconds; they add up to the sweep's wall time)")
    print("| phase | s | share of the whole |")
    print("|---|---|---|")
    for name, v in phases:
        pct = "—" if v is None else f"{100 * v / whole:.1f} %"
        print(f"| {name} | {fmt(v)} | {pct} |")
    print(f"| **whole (the timed phases)** | **{whole:.1f}** | 100 % |")
    if job.sweep_s is not None:
        print(f"| (the sweep's wall time) | {job.sweep_s:.1f} | {100 * job.sweep_s / whole:.1f} % |")
    share = 1 - sweep["training"] / whole if whole else None
    print(f"\nnon-training share: {fmt(None if share is None else 100 * share)} % of the whole (goal <= 10 %)"
          + ("" if install_s is not None else "; install not included (--install-s)"))
    for note in job.notes:
        print(f"# {note}")
    missing = [name for name, v in phases if v is None]
    if missing:
        print(f"# not timed, left out of the whole: {', '.join(missing)}")
    return share


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="a config override for every command (as `bronchopose --set`)")
    parser.add_argument("--project", type=Path, help="read this finished project instead of running the main job")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--install-s", type=float, help="the install's seconds, measured apart")
    parser.add_argument("--keep", type=Path, help="run in this (new) folder and keep it")
    args = parser.parse_args()
    print(f"# {cpu_line()}", flush=True)
    if args.project is not None:
        print_phases(read_project(args.project.resolve(), args.overrides, args.workers), args.install_s)
        return
    with tempfile.TemporaryDirectory(prefix="bench-phases-") as tmp:
        root = args.keep.resolve() if args.keep else Path(tmp)
        job = run_main_job(root, args.overrides, workers=args.workers)
        print_phases(job, args.install_s)
        print(f"# {cpu_line()} (at the end)")


if __name__ == "__main__":
    main()
