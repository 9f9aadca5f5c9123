"""Worker idle time of a sweep's claim order: the grid order against ``sweep.order.claim_order``.

    python benchmarks/bench_claims.py [--config experiments.yaml] [--workers 2] [--settings FILE]

Each cell's duration is its expected cost (budget over its architecture's measured training rate in the speed
settings file, as ``sweep/order.py`` computes it) times ``--slowdown`` for a cell that runs beside another
cell of the same architecture (issue 31 measured ConvLSTM at 40-42 pairs/s beside another ConvLSTM, 61 beside
an OffsetNet on 2 cores: 0.67). Workers take the next cell in order whenever they are free (the claims table);
prints the makespan and the idle time (workers waiting while work remains = makespan x workers - busy time)
for both orders. A simulation from measured rates, not a run: the machine this was written on was shared.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bronchocli.config import load_config  # noqa: E402
from bronchocli.sweep.order import claim_order, expected_costs  # noqa: E402
from bronchocli.sweep.plan import plan_cells  # noqa: E402


def simulate(order, cost, workers: int, slowdown: float) -> tuple[float, float]:
    """(makespan, idle seconds): event by event, a cell's rate slowed while a same-architecture cell runs."""
    queue, running, t, busy = list(order), [], 0.0, 0.0
    while queue or running:
        while queue and len(running) < workers:
            c = queue.pop(0)
            running.append([c, cost[c.key]])  # work left, in seconds at full rate
        archs = [c.arch for c, _ in running]
        speed = [slowdown if archs.count(c.arch) > 1 else 1.0 for c, _ in running]
        dt = min(left / s for (_, left), s in zip(running, speed))
        for r, s in zip(running, speed):
            r[1] -= dt * s
        busy += dt * len(running)
        t += dt
        running = [r for r in running if r[1] > 1e-9]
    return t, t * workers - busy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="experiments.yaml")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--settings", default=None, help="a speed settings file (default: the shipped one)")
    ap.add_argument("--slowdown", type=float, default=0.67)
    a = ap.parse_args()
    cfg = load_config(a.config)
    if a.settings:
        cfg = cfg.with_values({"train.speed_settings": a.settings})
    cells = plan_cells(cfg)
    cost = expected_costs(cfg, cells)
    if cost is None:
        sys.exit("no measured training rates for these architectures: run `bronchopose profile --speed` first")
    print(f"| order | claim sequence | makespan s | idle s ({a.workers} workers) |\n|---|---|---|---|")
    for name, order in (("grid", cells), ("claim_order", claim_order(cfg, cells))):
        span, idle = simulate(order, cost, a.workers, a.slowdown)
        print(f"| {name} | {' '.join(c.arch[:4] + str(c.seed) for c in order)} | {span:.0f} | {idle:.0f} |")


if __name__ == "__main__":
    main()
