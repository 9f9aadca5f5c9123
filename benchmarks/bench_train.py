"""CPU training throughput (bare step vs engine), tracking latency, and the overhead of a whole tracked run.

    python benchmarks/bench_train.py [--sizes 64 128] [--threads 2] [--seconds 8] [--steps 40] [--skip-run]
    python benchmarks/bench_train.py --curves [--steps 60] [--val-every 30] [--repeats 3]

1. **Training pairs/s** per architecture and size (engine_bench.py says what is timed): the bare optimiser
   step on a fixed in-memory batch, and the engine (``Trainer.fit``: batch order, frame gathering,
   schedule, validation with BatchNorm re-estimation every ``--val-every`` steps); engine / bare is what
   the engine costs. 20 image pairs per step for every architecture (temporal: 2 windows of 10).
2. **Tracking latency** (batch 1, eval mode): one new frame arrives, the model predicts the pair
   (previous, current); recurrent models carry their state. Median over 30 frames.
3. **Whole-run overhead**: two real ``run_cell`` runs of the baseline on a small rendered dataset (cold: the
   first creates the MLflow store and the frame cache; warm: the next, as in a sweep). Overhead = wall time
   minus training and validation time: start-up, data preparation, checkpoints, MLflow tracking, test
   evaluation (goal: < 10 % of the training time).
4. **Curve logging** (``--curves``, instead of 1-3): ``Trainer.fit`` of the baseline at 64² with the training
   curves (``runs.log_every`` 10) and system metrics (10 s samples) logged to a real SQLite MLflow run ("on")
   vs curve points at validations only and no system metrics ("off"), interleaved ``--repeats`` times;
   the median step time (training time / steps) and the time with validations and their logging, on / off;
   and the MLflow metric rows each run gained.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import textwrap
import time
from pathlib import Path

import torch
from engine_bench import bare_step_rate, engine_rate

from bronchocli.config import Config, load_config
from bronchocli.generation import ensure_dataset
from bronchocli.models import build_model
from bronchocli.registry import arch_names
from bronchocli.runs.client import MetricBuffer, client_for, experiment_id
from bronchocli.runs.system import system_metrics
from bronchocli.training.run import run_cell


@torch.no_grad()
def track_latency(arch: str, size: int, frames: int = 30) -> float:
    model = build_model(arch, image_size=size).to(memory_format=torch.channels_last).eval()
    video = torch.randn(frames + 1, 3, size, size)
    state, times = None, []
    for t in range(frames):
        t0 = time.perf_counter()
        _, state = model(video[t: t + 2].unsqueeze(0), state)
        times.append(time.perf_counter() - t0)
    return statistics.median(times[3:])


CONFIG = """\
    name: bench-run
    dataset:
      root: data
      generate: {{patients: 2, lobes: [ur, br, ul, bl], trajectories: 6, image_size: 64, step_mm: [2.0, 4.0],
                 max_frames: 24, workers: 2}}
    splits: {{train: 4, val: 1, test: 1}}
    train: {{steps: {steps}, batch_size: 20, val_every: 50}}
    runs: {{model_artifact: none}}
"""


def whole_run(steps: int) -> list[dict[str, float]]:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "experiments.yaml").write_text(textwrap.dedent(CONFIG.format(steps=steps)))
        cfg = load_config(root / "experiments.yaml")
        ensure_dataset(cfg, progress=False)
        out = []
        for seed in (0, 1):  # cold: creates the MLflow store and the frame cache; warm: a sweep's next cell
            t0 = time.perf_counter()
            result = run_cell(cfg, cfg.cell(arch="baseline", rot_loss="mse", population="personalized", seed=seed),
                              progress=False)
            m = result.metrics
            out.append({"wall_s": time.perf_counter() - t0, "train_s": m["train.time_s"],
                        "val_s": m["train.val_time_s"], "eval_s": m["eval.time_s"], "steps": m["train.steps"]})
    return out


def curve_overhead(steps: int, val_every: int, repeats: int, size: int = 64) -> None:
    """Step time with curve + system-metric logging on vs off (see the module doc, 4.)."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Config(name="bench-curves").with_values({"runs.uri": f"sqlite:///{tmp}/mlflow.db",
                                                       "runs.artifacts": f"{tmp}/artifacts"})
        client = client_for(cfg)
        exp = experiment_id(client, cfg)
        times: dict[str, list[tuple[float, float]]] = {"off": [], "on": []}
        rows: dict[str, list[int]] = {"off": [], "on": []}
        cpu = torch.device("cpu")
        engine_rate("baseline", size, 20, cpu, "32", 3, val_every=3)  # warm-up: allocator, threads, kernels
        for r in range(repeats):
            for mode in ("off", "on") if r % 2 == 0 else ("on", "off"):
                run_id = client.create_run(exp).info.run_id
                log_every = 10 if mode == "on" else 0
                sysm = cfg.with_values({"runs.system_metrics": mode == "on"})
                with system_metrics(sysm, run_id):
                    res = engine_rate("baseline", size, 20, cpu, "32", steps, val_every=val_every,
                                      log_every=log_every, on_curves=MetricBuffer(client, run_id).log_points)
                client.set_terminated(run_id)
                times[mode].append((res.train_s / res.steps, (res.train_s + res.val_s) / res.steps))
                run = client.get_run(run_id)
                rows[mode].append(sum(len(client.get_metric_history(run_id, k)) for k in run.data.metrics))
    step = {m: statistics.median(t[0] for t in v) for m, v in times.items()}
    whole = {m: statistics.median(t[1] for t in v) for m, v in times.items()}
    print(f"\nbaseline {size}², 20 pairs/step, {steps} steps, a validation every {val_every}, {repeats} runs each")
    print("| logging | step ms (training) | step ms (with validations + logging) | MLflow metric rows per run |")
    print("|---|---|---|---|")
    for m in ("off", "on"):
        print(f"| {m} | {1e3 * step[m]:.1f} | {1e3 * whole[m]:.1f} | {statistics.median(rows[m]):.0f} |")
    print(f"| on / off | {step['on'] / step['off']:.3f} | {whole['on'] / whole['off']:.3f} | "
          f"+{statistics.median(rows['on']) - statistics.median(rows['off']):.0f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=8.0, help="bare-step timing per measurement")
    parser.add_argument("--steps", type=int, default=40, help="engine optimiser steps per measurement")
    parser.add_argument("--val-every", type=int, default=50)
    parser.add_argument("--run-steps", type=int, default=150, help="steps of each whole run")
    parser.add_argument("--archs", nargs="+", default=list(arch_names()))
    parser.add_argument("--skip-run", action="store_true")
    parser.add_argument("--curves", action="store_true", help="only: step time with curve logging on vs off")
    parser.add_argument("--repeats", type=int, default=3, help="--curves: runs per mode")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.curves:
        curve_overhead(args.steps, args.val_every, args.repeats)
        return
    cpu = torch.device("cpu")
    print(f"machine: {platform.node()} {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{args.threads} threads")
    print("\n| arch | size | bare pairs/s | engine pairs/s | engine / bare | tracking ms/pair (batch 1) |")
    print("|---|---|---|---|---|---|")
    for size in args.sizes:
        for arch in args.archs:
            bare = bare_step_rate(arch, size, 20, cpu, "32", args.seconds)
            eng = engine_rate(arch, size, 20, cpu, "32", args.steps, val_every=args.val_every)
            lat = track_latency(arch, size)
            print(f"| {arch} | {size} | {bare:.1f} | {eng.pairs_per_s:.1f} | {eng.pairs_per_s / bare:.2f} | "
                  f"{lat * 1e3:.1f} |", flush=True)
    if not args.skip_run:
        for name, r in zip(("cold", "warm"), whole_run(args.run_steps)):
            training = r["train_s"] + r["val_s"]
            overhead = r["wall_s"] - training
            print(f"\nwhole run, {name} (baseline, 64², {r['steps']:.0f} steps): wall {r['wall_s']:.1f} s, training "
                  f"{r['train_s']:.1f} s + validation {r['val_s']:.1f} s, test evaluation {r['eval_s']:.1f} s; "
                  f"overhead {overhead:.1f} s = {100 * overhead / training:.1f} % of the training time")


if __name__ == "__main__":
    main()
