"""Training-batch throughput of the data pipeline alone, and what the baseline model consumes.

    python benchmarks/bench_data.py [--sizes 64 128] [--batch 16] [--seconds 10] [--no-model] [--augment]

Renders a small dataset (2 procedural patients x 4 lobes x 6 trajectories x
up to 41 frames at the largest size) to a temporary directory, builds the
frame cache at each size (not timed: it happens once per dataset and size),
then times what the training loop does per batch (bronchocli.data.batches):
``BatchOrder`` picks a shuffled batch of samples and ``FrameSource`` gathers
their frames from the memory-mapped cache on the CPU - batches of
independent pairs (``windows(..., 1)``, what the baseline and OffsetNet train
on) and of 10-pair windows (temporal models), as delivered uint8 batches
(``--augment`` adds the photometric augmentation). The baseline model's
training consumption is the pairs/s of Adam steps (forward + backward) on
float batches of the same size, measured in this process with torch's
default threads. The issue asks that the pipeline deliver at least 5x what
the model consumes.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from bronchocli.config import Config
from bronchocli.data.batches import BatchOrder, FrameSource, Photometric, Samples, windows
from bronchocli.data.cache import FrameCache
from bronchocli.data.reader import open_dataset_dir
from bronchocli.generation.pipeline import generate_dataset
from bronchocli.models import build_model


def pipeline_rate(samples: Samples, source: FrameSource, batch_pairs: int, seconds: float,
                  augment: bool = False) -> float:
    """Image pairs per second of shuffled batches of ``batch_pairs`` pairs (after one warm-up batch)."""
    order = BatchOrder(len(samples), max(1, batch_pairs // samples.n_pairs), seed=0)
    photometric, generator = Photometric(), torch.Generator().manual_seed(0)
    pairs, i, start = 0, 0, None
    while start is None or time.perf_counter() - start < seconds:
        idx = order(i)
        frames = source(samples.frames[idx])
        if augment:
            frames = photometric(frames, generator)
        i += 1
        if start is None:  # the first batch pays for paging the cache in
            start = time.perf_counter()
            continue
        pairs += len(idx) * samples.n_pairs
    return pairs / (time.perf_counter() - start)


def model_rate(size: int, batch: int, seconds: float) -> float:
    """Training pairs per second of the baseline model (Adam, forward + backward, float32)."""
    model = build_model("baseline", image_size=size).train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    frames = torch.rand(batch, 2, 3, size, size)
    target = torch.zeros(batch, 1, 6)

    def step() -> None:
        opt.zero_grad()
        poses, _ = model(frames)
        torch.nn.functional.mse_loss(poses, target).backward()
        opt.step()

    step()  # warm-up
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        step()
        steps += 1
    return steps * batch / (time.perf_counter() - start)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--batch", type=int, default=20, help="image pairs per batch (train.batch_size default)")
    ap.add_argument("--seconds", type=float, default=10.0, help="measuring time per figure")
    ap.add_argument("--no-model", action="store_true", help="skip the baseline model's consumption")
    ap.add_argument("--augment", action="store_true", help="include the photometric augmentation")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Config(name="bench-data").with_values({"dataset.generate": {
            "patients": 2, "trajectories": 6, "image_size": max(args.sizes), "max_frames": 41, "workers": 2}})
        root = generate_dataset(cfg, root=Path(tmp) / "ds", progress=False)
        ds = open_dataset_dir(root)
        print(f"dataset: {ds.n_frames} frames, {len(ds.trajectories)} trajectories; batch {args.batch} pairs, "
              f"main process, torch threads {torch.get_num_threads()}")
        print("| size | pipeline pairs/s (pairs) | pipeline pairs/s (10-pair windows) | baseline trains pairs/s | ratio |")
        print("|---|---|---|---|---|")
        for size in args.sizes:
            cache = FrameCache.open_or_build(ds, size, Path(tmp) / "cache", progress=False)
            source = FrameSource(cache, "cpu")
            pairs = pipeline_rate(windows(ds.trajectories, 1), source, args.batch, args.seconds, args.augment)
            wins = pipeline_rate(windows(ds.trajectories, 10), source, args.batch, args.seconds, args.augment)
            if args.no_model:
                model, ratio = "-", "pending"
            else:
                rate = model_rate(size, args.batch, args.seconds)
                model, ratio = f"{rate:,.0f}", f"{pairs / rate:,.0f}x"
            print(f"| {size}x{size} | {pairs:,.0f} | {wins:,.0f} | {model} | {ratio} |", flush=True)


if __name__ == "__main__":
    main()
