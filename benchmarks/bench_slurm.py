"""Overheads of `bronchopose sweep --launcher slurm` on a real single-node Slurm (the test cluster, two fake GPUs).

Measures, with the claims table on the local PostgreSQL and MLflow in a SQLite
file (shared-filesystem opt-in):

- submit -> first claim: from starting `bronchopose sweep --launcher slurm
  --detach` to the first cell claimed by an array task (config check, MLflow
  store, claims rows, sbatch, Slurm's scheduling, the task's Python start-up);
- submit -> first step: the same to the end of the first optimiser step of a
  real (tiny) training cell (its first checkpoint, val_every=1), so torch's
  import and the dataset's load are included;
- per-cell overhead: wall time per cell inside one task minus the time in the
  runner (claim, MLflow run bookkeeping, finish), with a runner that does no work.

    PYTHONPATH=.:tests:tests/sweep python benchmarks/bench_slurm.py [--cells 12]

Needs root, slurm-wlm and munge (as .ci/run installs them) and PostgreSQL at 127.0.0.1:5432.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import psycopg
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "tests" / "sweep")]

from slurm_cluster import start_cluster, stop_cluster  # noqa: E402
from tinydata import write_tiny_dataset  # noqa: E402

from bronchocli.config import load_config  # noqa: E402
from bronchocli.sweep import SweepStore  # noqa: E402

PG = "postgresql://postgres@127.0.0.1:5432/test"
MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"


def project(folder: Path, schema: str, cells: int, real: bool) -> Path:
    write_tiny_dataset(folder / "data" / "tiny", patients=2, lobes=("ur",), trajectories=4, frames=8, image_size=32)
    seeds = list(range(max(1, cells // 2)))
    data = {
        "name": "bench", "runs": {"uri": "sqlite:///mlflow.db", "artifacts": "artifacts"},
        "storage": {"url": f"{PG}?options=-csearch_path%3D{schema}"}, "dataset": {"root": "data/tiny"},
        "grid": {"arch": ["baseline"] if real else ["baseline", "lstm"], "rot_loss": ["mse"],
                 "population": ["personalized"], "seed": [0] if real else seeds},
        "splits": {"train": 2, "val": 1, "test": 1, "cross_subject_val": 1},
        "data": {"window": 3, "cache_dir": "cache"},
        "train": {"batch_size": 3, "steps": 4, "val_every": 1, "bn_recalibrate": 1, "threads": 1},
        "sweep": {"heartbeat_s": 1.0, "stale_after_s": 30.0, "poll_s": 0.2,
                  "launchers": {"slurm": {"cpus_per_task": 1, "shared_filesystem": True, "tasks": 2}}},
    }
    path = folder / "experiments.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def submit(path: Path, env: dict, runner: list[str]) -> tuple[float, float]:
    """Run the submit command; returns when it started and when it returned (its jobs are queued by then)."""
    t0 = time.time()
    subprocess.run([sys.executable, "-c", MAIN, "sweep", "-c", str(path), "--launcher", "slurm", "--detach", *runner],
                   cwd=path.parent, env=env, check=True, capture_output=True, timeout=300)
    return t0, time.time()


def wait(predicate, limit: float = 600.0) -> None:
    end = time.monotonic() + limit
    while not predicate():
        if time.monotonic() > end:
            raise SystemExit("benchmark: gave up waiting")
        time.sleep(0.05)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=12)
    args = ap.parse_args()
    admin = psycopg.connect(PG, autocommit=True)
    cluster = start_cluster(cpus=4, gpus=2)
    schemas = []
    try:
        env = {**os.environ, "SLURM_CONF": str(cluster.conf),
               "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests" / "sweep"), os.environ.get("PYTHONPATH", "")])}
        with tempfile.TemporaryDirectory() as tmp:
            # fake runner: the launcher's own overheads
            schema = f"bench_{uuid.uuid4().hex[:8]}"
            schemas.append(schema)
            admin.execute(f"CREATE SCHEMA {schema}")
            fake = Path(tmp) / "fake"
            (fake / "x").mkdir(parents=True)
            path = project(Path(tmp) / "x", schema, args.cells, real=False)
            fenv = {**env, "SWEEP_FAKE_DIR": str(fake / "x")}
            t0, queued = submit(path, fenv, ["--runner", "sweep_fakes:fake_runner"])
            cfg = load_config(path)
            store = SweepStore(cfg.paths.storage_url)
            wait(lambda: any(r.claimed_at for r in store.rows(cfg.name)))
            first_claim = min(r.claimed_at for r in store.rows(cfg.name) if r.claimed_at) - t0
            wait(lambda: all(r.state == "finished" for r in store.rows(cfg.name)))
            cluster.wait_idle_queue(300)
            rows = store.rows(cfg.name)
            by_worker: dict[str, list] = {}
            for r in rows:
                by_worker.setdefault(r.worker, []).append(r)
            per_cell = []
            for group in by_worker.values():
                group.sort(key=lambda r: r.claimed_at)
                if len(group) > 1:
                    wall = group[-1].finished_at - group[0].claimed_at
                    per_cell.append(wall / len(group) - statistics.mean(r.duration_s for r in group))
            # real training: submit -> first optimiser step
            schema = f"bench_{uuid.uuid4().hex[:8]}"
            schemas.append(schema)
            admin.execute(f"CREATE SCHEMA {schema}")
            path = project(Path(tmp) / "real", schema, 1, real=True)
            t1, _ = submit(path, env, [])
            rcfg = load_config(path)
            wait(lambda: any(rcfg.paths.checkpoints.glob("*/last.pt")))
            first_step = time.time() - t1
            cluster.wait_idle_queue(300)
        print(f"cells {len(rows)} (fake runner) in {len(by_worker)} tasks")
        print(f"submit -> first claim       {first_claim:6.1f} s  (of which the submit command "
              f"{queued - t0:.1f} s, queued -> first claim {first_claim - (queued - t0):.1f} s)")
        print(f"submit -> first step (real) {first_step:6.1f} s  (first checkpoint after step 1 and one validation)")
        print(f"per-cell overhead           {statistics.mean(per_cell):6.2f} s  (per task: "
              + ", ".join(f"{v:.2f}" for v in per_cell) + ")")
    finally:
        stop_cluster(cluster)
        for schema in schemas:
            admin.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")
        admin.close()


if __name__ == "__main__":
    main()
