"""Orchestration overhead of `bronchopose sweep` per cell: wall time minus time inside the cell runner.

    python benchmarks/bench_sweep.py [--cells 5 40] [--workers 1 2] [--storage URL] [--real]

Runs the real command (`bronchopose sweep`) in a subprocess on a fresh sweep, with the no-op runner of
sweep_noop.py (named by ``--runner sweep_noop:noop_runner``) that only creates and finishes
an MLflow run (inside-runner time, recorded per cell in the claims table). For
each worker count it runs two sweep sizes and reports

- fixed cost: wall − runner time of the small sweep minus its per-cell part
  (interpreter and imports, plan, spawning workers, MLflow client start-up);
- **overhead per cell**: the slope of (wall − runner time / workers) between the
  two sizes — what claiming, heartbeat, recording and the live view add to each
  cell (goal: < 1 s on SQLite).

The MLflow store's one-time creation (its schema migration) is done before the
timings and reported apart, and so is rendering the tiny dataset. With
``--real`` it also runs two tiny real training cells with one worker and
reports (wall − Σ run time) / cells, fixed costs included.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ARCHS = ["baseline", "lstm", "convlstm", "conv3d", "offsetnet"]


def write_config(root: Path, storage: str, real: bool) -> Path:
    import yaml

    cfg = {
        "name": "bench",
        "runs": {"uri": "sqlite:///mlflow.db", "artifacts": "artifacts", "checkpoints": "ckpt"},
        "storage": {"url": storage},
        "dataset": {"root": "data/tiny", "generate": {"patients": 2, "lobes": ["ur"], "trajectories": 4,
                                                      "image_size": 32, "max_frames": 8, "workers": 1}},
        "grid": {"arch": ARCHS, "rot_loss": ["mse"], "population": ["personalized"]},
        "sweep": {"heartbeat_s": 2, "stale_after_s": 30, "poll_s": 0.5},
    }
    if real:
        cfg.update(splits={"train": 2, "val": 1, "test": 1, "cross_subject_val": 1},
                   data={"window": 3, "cache_dir": "cache"},
                   train={"batch_size": 3, "steps": 2, "val_every": 2, "bn_recalibrate": 1})
    path = root / "experiments.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def sweep(config: Path, name: str, cells: int, workers: int, runner: str | None, extra: list[str],
          expect: int | None = None) -> tuple[float, float]:
    """Run one fresh sweep of ``cells`` cells; returns (wall s, Σ runner s)."""
    from bronchocli.config import load_config
    from bronchocli.sweep import SweepStore

    seeds = list(range(max(1, cells // len(ARCHS))))
    args = ["--set", f"name={name}", "--set", f"grid.seed={seeds}", "--workers", str(workers), *extra]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}
    if runner:
        args += ["--runner", runner]
    code = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code, "sweep", "-c", str(config), *args], capture_output=True,
                         text=True, env=env)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise SystemExit(f"sweep failed ({out.returncode}):\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}")
    cfg = load_config(config, overrides=[f"name={name}"])
    rows = SweepStore(cfg.paths.storage_url).rows(name)
    assert len(rows) == (expect or len(seeds) * len(ARCHS)) and all(r.state == "finished" for r in rows)
    return wall, sum(r.duration_s or 0.0 for r in rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, nargs=2, default=[5, 40], help="small and large sweep sizes (multiples of 5)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--storage", default="sqlite:///sweep.db", help="claims database (default: SQLite in a temp dir)")
    ap.add_argument("--real", action="store_true", help="also time two tiny real training cells")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        config = write_config(root, args.storage, real=False)
        from bronchocli.config import load_config
        from bronchocli.generation import ensure_dataset
        from bronchocli.runs.client import client_for, experiment_id

        ensure_dataset(load_config(config), progress=False)  # rendered once, not timed
        t0 = time.perf_counter()
        experiment_id(client_for(load_config(config)), load_config(config))
        print(f"MLflow store creation (once per store, not timed below): {time.perf_counter() - t0:.1f} s")
        print(f"cpu cores: {os.cpu_count()}; storage: {args.storage.split('://')[0]}\n")
        print("| workers | cells | wall s | Σ runner s | wall − runner/workers s | overhead per cell s | fixed s |")
        print("|---|---|---|---|---|---|---|")
        n = 0
        for workers in args.workers:
            points = []
            for cells in args.cells:
                n += 1
                wall, inside = sweep(config, f"bench{n}", cells, workers, "sweep_noop:noop_runner", [])
                points.append((cells, wall, inside, wall - inside / workers))
            (c1, _, _, o1), (c2, _, _, o2) = points
            per_cell = (o2 - o1) / (c2 - c1)
            fixed = o1 - per_cell * c1
            for cells, wall, inside, over in points:
                print(f"| {workers} | {cells} | {wall:.1f} | {inside:.2f} | {over:.1f} | {per_cell:.3f} "
                      f"| {fixed:.1f} |")
        if args.real:
            real_cfg = write_config(root, args.storage, real=True)
            ensure_dataset(load_config(real_cfg), progress=False)
            wall, inside = sweep(real_cfg, "bench-real", 5, 1, None, ["--only", "arch=baseline,lstm"], expect=2)
            print(f"\nreal tiny runs (baseline + lstm, 1 worker): wall {wall:.1f} s, Σ run_cell {inside:.1f} s, "
                  f"(wall − runs) / cell {(wall - inside) / 2:.1f} s (fixed costs included)")


if __name__ == "__main__":
    main()
