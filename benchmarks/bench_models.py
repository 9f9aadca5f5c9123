"""Latency, GMAC, parameters and peak memory of every architecture at 64², 128² and 256² (the ablation table).

Run: ``python benchmarks/bench_models.py [--sizes 64 128 256] [--device cpu|cuda] [--batch 4]
[--window 10] [--repeats 3] [--precision 32] [--threads N]``. Prints one Markdown table per
image size (the rows of ``bronchopose profile``; see bronchocli/models/profile.py for the method).
Results: benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import platform
import time

import torch

from bronchocli.models import ARCHITECTURES
from bronchocli.models import profile as profiling


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--arch", nargs="+", default=list(ARCHITECTURES))
    ap.add_argument("--device", default="cpu", choices=profiling.DEVICES)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--window", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--precision", default="32", choices=profiling.PRECISIONS)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"# bench_models: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads\n")
    for size in args.sizes:
        start = time.perf_counter()
        rows = [
            profiling.profile_arch(name, size, args.device, args.batch, args.repeats, window=args.window,
                                   warmup=args.warmup, precision=args.precision)
            for name in args.arch
        ]
        print(f"## {size}x{size}\n\n{profiling.markdown_table(rows)}\n\n{profiling.caption(rows)}. "
              f"({time.perf_counter() - start:.0f} s)\n", flush=True)


if __name__ == "__main__":
    main()
