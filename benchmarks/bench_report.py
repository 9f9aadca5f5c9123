"""Time to build every report table from a sweep of 500 MLflow runs (goal: under 3 s).

    python benchmarks/bench_report.py [--runs 500] [--store DIR] [--repeats 3] [--no-cli]

Fabricates a paper-sized sweep on a SQLite MLflow store (tests/reporting/
report_fakes.py, the same fabricator as the golden tests): 5 architectures x
3 rotation losses x (personalized + 5 cross-subject folds) x 5 seeds = 450
cells, plus duplicate runs up to ``--runs``; each run carries ~100 params, the
~40 final metrics training logs and its tags (what ``search_runs`` must
load). ``--store DIR`` keeps the store there and reuses it on the next call.

Figures reported (median of ``--repeats``):
* ``collect``: ``collect_runs`` - the one paginated ``search_runs`` query and
  the deduplication, with the MLflow client already connected;
* ``tables``: building every table for both evaluations and rendering and
  writing Markdown + LaTeX (16 files);
* ``report (in process)``: both of the above - the issue's "build all tables";
* ``CLI``: ``bronchopose report --table all --no-figures --no-latency -q`` as a
  subprocess, wall clock including Python start-up, imports (torch is pulled
  in by the CLI module) and connecting to the store.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "reporting"))

from report_fakes import fabricate_run, metrics_from  # noqa: E402

from bronchocli.reporting import collect, tables  # noqa: E402
from bronchocli.reporting.report import build_tables, write_tables  # noqa: E402

ARCHS = ("baseline", "lstm", "convlstm", "conv3d", "offsetnet")
LOSSES = ("mse", "de", "ce")
FOLDS = ("p00", "p01", "p02", "p03", "p04")
SEEDS = range(5)
SWEEP, EXPERIMENT = "bench", "bench-exp"
PROFILES = {a: {"params": 14e6, "latency_ms_b1": 4.0, "gmacs_per_pair": 0.4, "device": "cpu", "image_size": 256,
                "window": 10, "batch": 8, "precision": "32"} for a in ARCHS}


def _extra_metrics(i: int) -> dict[str, float]:
    """The rest of what a training run logs at step 0 (traj.*, mm metrics, geodesic, timings)."""
    out = {f"{p}.{m}.{s}": 0.1 * (i % 7 + 1) for p in ("pair", "acc") for m in ("pos_l2_mm", "geodesic")
           for s in ("mean", "std")}
    out |= {f"traj.{m}.{s}": 1.0 + i % 5 for m in ("ctf", "ctf_mm", "ate", "ate_mm", "rpe_trans", "rpe_rot", "drift")
            for s in ("mean", "std")}
    out |= {"train.time_s": 100.0, "train.epochs": 10.0, "train.pairs_per_s": 300.0, "val_best.loss": 0.5,
            "eval.time_s": 5.0, "zero_motion.pair.pos_l2.mean": 1.0, "zero_motion.acc.pos_l2.mean": 9.0}
    return out


def cells() -> list[tuple[str, str, str, str, int]]:
    out = []
    for seed in SEEDS:
        for arch in ARCHS:
            for loss in LOSSES:
                out.append((arch, loss, "personalized", "", seed))
                out += [(arch, loss, "cross-subject", f, seed) for f in FOLDS]
    return out


def fabricate(root: Path, n_runs: int) -> str:
    """Create (or reuse) the store under ``root``; returns its tracking URI."""
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{root / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    exp = client.get_experiment_by_name(EXPERIMENT)
    if exp is not None:
        return uri
    exp_id = client.create_experiment(EXPERIMENT, artifact_location=(root / "artifacts").as_uri())
    grid = cells()
    params = {f"section{k // 10}.key{k}": str(k) for k in range(100)}
    t0 = time.perf_counter()
    for i in range(n_runs):
        arch, loss, pop, fold, seed = grid[i % len(grid)]
        acc = (2.0 + i % 11 * 0.1, 10.0 + i % 13, 0.1 + i % 7 * 0.01, 0.02 + i % 5 * 0.001)
        metrics = metrics_from(acc, 12, 468, n_params=14_000_000) | _extra_metrics(i)
        fabricate_run(client, exp_id, arch=arch, rot_loss=loss, population=pop, fold=fold, seed=seed, sweep=SWEEP,
                      metrics=metrics, params=params, start_time=1_700_000_000_000 + i * 1000)
        if (i + 1) % 100 == 0:
            print(f"  fabricated {i + 1}/{n_runs} runs ({time.perf_counter() - t0:.0f} s)", flush=True)
    return uri


def time_in_process(uri: str, out: Path) -> tuple[float, float]:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    client.get_experiment_by_name(EXPERIMENT)  # connect (schema check) outside the timing
    t0 = time.perf_counter()
    index = collect.collect_runs(client, EXPERIMENT, SWEEP)
    t1 = time.perf_counter()
    ctx = tables.ReportContext(index, profiler=PROFILES.get)
    write_tables(build_tables(ctx, list(tables.TABLES), ["accumulated", "pair"]), out, ["md", "tex"])
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1


def time_cli(uri: str, out: Path) -> float:
    cfg = out / "bench.yaml"
    cfg.write_text(f"name: {SWEEP}\nruns:\n  uri: {uri}\n  experiment: {EXPERIMENT}\n")
    env = {**os.environ, "NO_COLOR": "1"}
    code = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code, "report", "-c", str(cfg), "--sweep", SWEEP, "--table", "all",
                    "--no-figures", "--no-latency", "-q", "--out", str(out / "cli")], check=True, capture_output=True,
                   env=env)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=500)
    ap.add_argument("--store", type=Path, default=None, help="keep/reuse the fabricated store here")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-cli", action="store_true")
    args = ap.parse_args()
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    with tempfile.TemporaryDirectory() as tmp:
        root = args.store or Path(tmp) / "store"
        root.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        uri = fabricate(root, args.runs)
        print(f"store: {root} ({time.perf_counter() - t0:.1f} s to fabricate or open)")
        out = Path(tmp) / "reports"
        collects, builds = zip(*(time_in_process(uri, out) for _ in range(args.repeats)))
        rows = [("collect (1 query + dedup)", statistics.median(collects)),
                ("tables (16 md/tex files)", statistics.median(builds)),
                ("report (in process)", statistics.median([a + b for a, b in zip(collects, builds)]))]
        if not args.no_cli:
            rows.append(("CLI wall clock", statistics.median(time_cli(uri, out) for _ in range(args.repeats))))
        print(f"\n{args.runs} runs, median of {args.repeats}:")
        for name, seconds in rows:
            print(f"  {name:<28} {seconds:7.3f} s")


if __name__ == "__main__":
    main()
