"""Operations dispatched per optimiser step, per architecture: what a launch-bound GPU step pays for.

    python benchmarks/bench_ops.py [--archs ...] [--precision bf16-mixed] [--size 32] [--explain]

Counts every ATen operation one steady-state optimiser step of ``training.loop.Trainer`` dispatches
(forward, loss, backward, fused Adam; ``diagnostics.dispatch.OpCounter``) on the CPU, with the non-finite
check at its CUDA interval: each would be a kernel launch (or a host sync) on a GPU. Op counts do not
depend on the image size; 4 image pairs per step (temporal models: 2 windows of 2 pairs).
``--explain``: also the graph and graph-break counts of ``torch.compile`` for each model's forward
(``torch._dynamo.explain``: no code generation). Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bronchocli.data.batches import FrameSource, Samples
from bronchocli.data.cache import FrameCache
from bronchocli.diagnostics.dispatch import OpCounter
from bronchocli.models import ARCHITECTURES, build_model
from bronchocli.training.loop import Settings, Trainer
from bronchocli.training.network import PoseRegressor

PAIRS, WINDOW = 4, 2


def trainer(arch: str, precision: str, cache: FrameCache) -> Trainer:
    torch.manual_seed(0)
    model = build_model(arch, image_size=cache.shape[-1], dropout=0.1).to(memory_format=torch.channels_last)
    net = PoseRegressor(model, (0.5,) * 3, (0.25,) * 3, standardized=True)
    pairs = WINDOW if net.temporal else 1
    rng = np.random.default_rng(0)
    n = PAIRS // pairs * 4
    idx = rng.integers(0, len(cache) - pairs - 1, n)[:, None] + np.arange(pairs + 1)[None]
    zeros = np.zeros(n, dtype=np.int64)
    train = Samples(idx, rng.normal(0, 1, (n, pairs, 6)).astype(np.float32), zeros, zeros, ("t",))
    s = Settings(steps=100, micro_pairs=PAIRS, accum=1, chunk=pairs, val_every=100, patience=None, min_delta=0.0,
                 lr=1e-4, weight_decay=0.0, warmup_steps=0, schedule="constant", rot_loss="ce", rot_weight=1.0,
                 precision=precision, bn_recalibrate=0, augment=False, seed=0)
    t = Trainer(net, train, train, FrameSource(cache, "cpu", "yes"), s, device=torch.device("cpu"))
    t.check_every = 25  # as on CUDA
    return t


def count(arch: str, precision: str, cache: FrameCache) -> OpCounter:
    t = trainer(arch, precision, cache)
    t._train_until(2)  # warm-up: the optimiser's lazy state
    with OpCounter() as ops:
        t._train_until(3)
    return ops


def explain(arch: str, size: int) -> tuple[int, int, float]:
    torch._dynamo.reset()
    model = build_model(arch, image_size=size).to(memory_format=torch.channels_last)
    net = PoseRegressor(model, (0.5,) * 3, (0.25,) * 3)
    frames = torch.randint(0, 256, (2, 3, 3, size, size), dtype=torch.uint8)
    t0 = time.perf_counter()
    out = torch._dynamo.explain(net)(frames)
    return out.graph_count, out.graph_break_count, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--archs", nargs="+", default=list(ARCHITECTURES))
    ap.add_argument("--precision", default="bf16-mixed", choices=["32", "bf16-mixed", "16-mixed"])
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--explain", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}; {args.precision}; {PAIRS} pairs per step; one steady-state step\n")
    print("| arch | ops per step | casts | views + detach | copies | host syncs |" +
          (" compiled graphs | graph breaks |" if args.explain else ""))
    print("|---|---|---|---|---|---|" + ("---|---|" if args.explain else ""))
    with tempfile.TemporaryDirectory() as tmp:
        arr = np.random.default_rng(0).integers(0, 256, (24, 3, args.size, args.size), dtype=np.uint8)
        np.save(Path(tmp) / "f.npy", arr)
        cache = FrameCache(Path(tmp) / "f.npy", arr.shape)
        for arch in args.archs:
            c = count(arch, args.precision, cache)
            row = f"| {arch} | {c.total} | {c.casts} | {c.views} | {c.copies} | {c.syncs} |"
            if args.explain:
                graphs, breaks, _ = explain(arch, args.size)
                row += f" {graphs} | {breaks} |"
            print(row, flush=True)


if __name__ == "__main__":
    main()
