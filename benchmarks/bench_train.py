"""CPU training throughput (bare step vs engine), tracking latency, and the overhead of a whole tracked run.

    python benchmarks/bench_train.py [--sizes 64 128] [--threads 2] [--seconds 8] [--steps 40] [--skip-run]

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

from bronchocli.config import load_config
from bronchocli.generation import ensure_dataset
from bronchocli.models import build_model
from bronchocli.registry import arch_names
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
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
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
