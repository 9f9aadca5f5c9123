"""What the benchmarks that run the real commands share (bench_share, bench_realised, bench_phases): the CPU they
ran on, the `bronchopose` CLI as a subprocess with a private claims folder, and the runs read back from a
project's MLflow store and sweep claims table.

A benchmark project is a folder with its own ``experiments.yaml`` (its own MLflow store and claims table under
``runs/``); the commands run with that folder as the working directory, so the config's relative paths resolve
inside it.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bronchocli.config import load_config
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.cores import machine_cores
from bronchocli.runs.records import search_runs
from bronchocli.speed import cpu_info, cpu_key

MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
FLAGS = ("amx_bf16", "avx512_bf16", "avx512f", "avx2")


def cpu_name() -> str:
    """``model name`` of /proc/cpuinfo (the processor string elsewhere)."""
    return next((line.split(":", 1)[1].strip() for line in cpu_info().splitlines() if line.startswith("model name")),
                platform.processor() or platform.machine())


def cpu_line() -> str:
    """One line naming the CPU: model name, cores, which of :data:`FLAGS` it has, its speed-settings key, load."""
    words = set(next((line.split(":", 1)[1].split() for line in cpu_info().splitlines() if line.startswith("flags")),
                     []))
    flags = ", ".join(f"{f} {'yes' if f in words else 'no'}" for f in FLAGS)
    return (f"CPU: {cpu_name()}, {machine_cores()} cores; {flags}; speed settings key {cpu_key()}; "
            f"load average {os.getloadavg()[0]:.1f}")


def private_env(root: Path) -> dict[str, str]:
    """The environment for the commands: a claims folder of their own (``XDG_RUNTIME_DIR`` under ``root``), so
    processes of the project outside the benchmark do not change the cores' shares; no inherited worker count."""
    claims = root / "claims"
    claims.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(claims), "OMP_NUM_THREADS": str(machine_cores())}
    env.pop("BRONCHOPOSE_CPU_WORKERS", None)
    return env


def start(folder: Path, env: dict[str, str], *argv: str, log: str = "command.log") -> subprocess.Popen:
    """``bronchopose *argv`` in ``folder``, its output in ``folder/log``."""
    out = open(folder / log, "w")  # noqa: SIM115 - the child holds it; closed when this process exits
    return subprocess.Popen([sys.executable, "-c", MAIN, *argv], cwd=folder, env=env, stdout=out,
                            stderr=subprocess.STDOUT)


def finish(procs: dict[str, tuple[Path, subprocess.Popen]]) -> float:
    """Wait for every process; SystemExit naming the log of one that failed. Returns the seconds waited."""
    t0 = time.perf_counter()
    for label, (folder, proc) in procs.items():
        if proc.wait() != 0:
            raise SystemExit(f"{label}: exit {proc.returncode}; see its log in {folder}")
    return time.perf_counter() - t0


def timed(folder: Path, env: dict[str, str], *argv: str, log: str) -> float:
    """Run ``bronchopose *argv`` to its end; its wall seconds (process start to exit); SystemExit on failure."""
    t0 = time.perf_counter()
    proc = start(folder, env, *argv, log=log)
    if proc.wait() != 0:
        raise SystemExit(f"bronchopose {' '.join(argv)}: exit {proc.returncode}; see {folder / log}")
    return time.perf_counter() - t0


def project_config(folder: Path, overrides: Sequence[str] = ()):
    """The project's config as its commands saw it (the same ``--set`` overrides)."""
    return load_config(folder / "experiments.yaml", overrides=list(overrides))


def cell_runs(folder: Path, overrides: Sequence[str] = ()) -> list[Any]:
    """The project's FINISHED training runs (MLflow ``Run`` objects with ``train.pairs_per_s``): a sweep's
    parent run and other bookkeeping runs are left out."""
    cfg = project_config(folder, overrides)
    client = client_for(cfg)
    runs = search_runs(client, [experiment_id(client, cfg)], statuses=["FINISHED"])
    return [r for r in runs if "train.pairs_per_s" in r.data.metrics]


def parent_runs(folder: Path, overrides: Sequence[str] = ()) -> list[Any]:
    """The project's sweep parent runs (tag ``run_kind`` = ``sweep``)."""
    cfg = project_config(folder, overrides)
    client = client_for(cfg)
    return [r for r in search_runs(client, [experiment_id(client, cfg)]) if r.data.tags.get("run_kind") == "sweep"]


def claim_rows(folder: Path, overrides: Sequence[str] = ()) -> list[Any]:
    """Every row of the project's sweep claims table (``storage.CellRow``: claimed_at, finished_at, worker, ...)."""
    from bronchocli.sweep.plan import open_store  # lazy: only the benchmarks that read a sweep need it

    store = open_store(project_config(folder, overrides))
    try:
        return [row for sweep in store.sweeps() for row in store.rows(sweep)]
    finally:
        store.close()
