"""Training throughput per architecture, inference latency, and the overhead of a whole tracked run.

    python benchmarks/bench_train.py [--sizes 64 128] [--threads 2] [--seconds 8] [--run-seconds 60] [--skip-run]

1. **Training pairs/s** (what each model consumes): the training step of
   ``PoseModule`` (normalisation, forward, pose loss, backward, fused Adam) on
   uint8 frame batches already in memory, as the engine runs it: pairwise
   models on batches of 16 pairs, temporal models on batches of 2 windows of
   10 pairs. Warm-up steps first, then steps for ``--seconds``.
2. **Tracking latency** (batch 1, eval mode): one new frame arrives, the model
   predicts the pair (previous, current); recurrent models carry their state.
   Median over 30 frames, reported as ms per pair and pairs/s (real time needs
   >= 30 pairs/s).
3. **Whole-run overhead** (``--run-seconds``, default a ~1 minute run): real
   ``run_cell`` runs of the baseline on a tiny dataset sized so training takes
   about that long (cold: the first run creates the MLflow store and frame
   cache; warm: the next run, as in a sweep). Training time = time inside
   training and validation steps; overhead = the rest of the run's wall time:
   start-up, data preparation, checkpointing, MLflow tracking and test
   evaluation (goal: < 10 % of the training time).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import torch

from bronchocli.config import ARCHS, load_config, make_cell
from bronchocli.models import build_model
from bronchocli.training.module import PoseModule


def train_rate(arch: str, size: int, seconds: float) -> float:
    model = build_model(arch, image_size=size).to(memory_format=torch.channels_last)
    module = PoseModule(model, rot_loss="ce", window=10)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4, fused=True)
    module.optimizers = lambda: opt  # the step without a Trainer: same maths as in training
    module.manual_backward = lambda loss: loss.backward()
    module.log = lambda *a, **k: None
    b, n = (2, 10) if model.temporal else (16, 1)
    batch = {"frames": torch.randint(0, 255, (b, n + 1, 3, size, size), dtype=torch.uint8),
             "labels": torch.randn(b, n, 6)}
    model.train()
    for _ in range(2):
        module.training_step(batch, 0)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or steps < 2:
        module.training_step(batch, 0)
        steps += 1
    return steps * b * n / (time.perf_counter() - t0)


@torch.no_grad()
def track_latency(arch: str, size: int, frames: int = 30) -> float:
    model = build_model(arch, image_size=size).to(memory_format=torch.channels_last).eval()
    video = torch.randn(frames + 1, 3, size, size)
    state, times = None, []
    for t in range(frames):
        t0 = time.perf_counter()
        _, state = model(video[t : t + 2].unsqueeze(0), state)
        times.append(time.perf_counter() - t0)
    return statistics.median(times[3:])


CONFIG = """\
    name: bench-run
    dataset: {{root: tiny}}
    splits: {{train: 4, val: 1, test: 1}}
    data: {{workers: 0, image_size: 64}}
    train: {{batch_size: 16, max_epochs: {epochs}, patience: 100}}
"""


def whole_run(seconds: float) -> list[dict[str, float]]:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from tinydata import write_tiny_dataset

    from bronchocli.training.run import run_cell

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_tiny_dataset(root / "tiny", patients=2, lobes=("ur", "br", "ul", "bl"), trajectories=6, frames=41,
                           image_size=64)
        epochs = max(1, round(seconds / 16))  # ~1280 training pairs per epoch at ~80 pairs/s
        (root / "experiments.yaml").write_text(textwrap.dedent(CONFIG.format(epochs=epochs)))
        cfg = load_config(root / "experiments.yaml")
        out = []
        for seed in (0, 1):  # cold: creates the MLflow store and the frame cache; warm: a sweep's next cell
            t0 = time.perf_counter()
            result = run_cell(cfg, make_cell(cfg, "baseline", "mse", "personalized", None, seed, "world"),
                              progress=False)
            wall = time.perf_counter() - t0
            m = result.metrics
            out.append({"wall_s": wall, "step_s": m["train.step_time_s"], "val_s": m["train.val_time_s"],
                        "fit_s": m["train.time_s"],
                        "eval_s": m["eval.time_s"], "epochs": m["train.epochs"]})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--run-seconds", type=float, default=60.0)
    parser.add_argument("--archs", nargs="+", default=list(ARCHS))
    parser.add_argument("--skip-run", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"machine: {platform.node()} {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{args.threads} threads")
    print("\n| arch | size | training pairs/s | tracking ms/pair (batch 1) | tracking pairs/s |")
    print("|---|---|---|---|---|")
    for size in args.sizes:
        for arch in args.archs:
            rate = train_rate(arch, size, args.seconds)
            lat = track_latency(arch, size)
            print(f"| {arch} | {size} | {rate:.1f} | {lat * 1e3:.1f} | {1 / lat:.1f} |", flush=True)
    if not args.skip_run:
        for name, r in zip(("cold", "warm"), whole_run(args.run_seconds)):
            training = r["step_s"] + r["val_s"]
            overhead = r["wall_s"] - training
            print(f"\nwhole run, {name} (baseline, 64², {r['epochs']:.0f} epochs): wall {r['wall_s']:.1f} s, "
                  f"training steps {r['step_s']:.1f} s + validation steps {r['val_s']:.1f} s, fit {r['fit_s']:.1f} s, "
                  f"test evaluation {r['eval_s']:.1f} s; overhead (start-up, data preparation, checkpointing, "
                  f"tracking, test evaluation) {overhead:.1f} s = {100 * overhead / training:.1f} % of the "
                  f"training time")


if __name__ == "__main__":
    main()
