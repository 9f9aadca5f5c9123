"""The cost of learning (issue 45): pairs seen and core-seconds until a run's validation headline first reaches
``COST_TARGET``. Defined here once; every run logs it as ``cost.*`` metrics (engine.py), and
``bronchopose tune``'s budgeted objective and benchmarks/README.md ("Cost of learning") read the same keys."""

from __future__ import annotations

import math

from .. import runkeys

# ``val.ratio.pos_l2`` (validation position error ÷ the training-mean predictor's on the same pairs) to reach
COST_TARGET = 0.90


def cost_of_learning(history: list[dict[str, float]], target: float = COST_TARGET) -> dict[str, float]:
    """Pairs seen and core-seconds (``train.core_s``: the process's CPU time over every thread in training steps,
    validations and checkpoints left out) at the first validation whose ``val.ratio.pos_l2`` is <= ``target``;
    empty when no validation reached it. The validation cadence bounds the resolution: state it with the numbers."""
    seen, core_s = runkeys.train("pairs_seen"), runkeys.train("core_s")
    for h in history:
        ratio = h.get(runkeys.VAL_RATIO, math.nan)
        if math.isfinite(ratio) and ratio <= target:
            out = {runkeys.cost("pairs", target): h[seen], runkeys.cost("step", target): h["step"]}
            if core_s in h:
                out[runkeys.cost("core_s", target)] = h[core_s]
            return out
    return {}


def cost_value(metrics: dict[str, float], target: float = COST_TARGET) -> float:
    """A run's cost of learning as one number to minimise (``tune.objective: cost``): the pairs seen until a
    validation reached ``target``; a run that never did, its pairs seen x (1 + its kept weights'
    ``val_best.ratio.pos_l2`` - ``target``), so it ranks behind every run that reached the target within as many
    pairs, and the closer it came the better. NaN when the run has no validation ratio."""
    reached = metrics.get(runkeys.cost("pairs", target))
    if reached is not None:
        return float(reached)
    ratio = metrics.get(runkeys.best_of(runkeys.VAL_RATIO), math.nan)
    seen = metrics.get(runkeys.train("pairs_seen"), math.nan)
    if not (math.isfinite(ratio) and math.isfinite(seen)):
        return math.nan
    return seen * (1.0 + max(0.0, ratio - target))
