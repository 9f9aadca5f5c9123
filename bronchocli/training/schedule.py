"""The learning-rate schedule of an optimiser step (``train.schedule``, ``train.warmup``), and Adam's beta1 where the
schedule cycles it.

* ``cosine`` (default) and ``constant``: a linear warm-up over ``train.warmup`` of the steps, then cosine decay to
  zero or a constant rate;
* ``onecycle``: one cycle (Smith & Topor 2019, as PyTorch's ``OneCycleLR`` with its defaults and cosine
  annealing): the warm-up fraction is its rising phase, from lr/25 to lr on a half cosine, then a half cosine down
  to lr/250,000; Adam's beta1 moves the other way, from 0.95 to 0.85 at the peak and back.

``s``: anything with ``steps``, ``warmup_steps`` and ``schedule`` (the loop's ``Settings``).
"""

from __future__ import annotations

import math
from typing import Any

# OneCycleLR's defaults (the module doc)
ONECYCLE_DIV = 25.0
ONECYCLE_FINAL_DIV = 1e4
ONECYCLE_BETA1 = (0.85, 0.95)  # (at the peak rate, at either end)


def _cos_between(start: float, end: float, pct: float) -> float:
    return end + (start - end) / 2.0 * (math.cos(math.pi * min(1.0, max(0.0, pct))) + 1.0)


def _onecycle_phase(step: int, s: Any) -> tuple[bool, float]:
    """(rising, fraction of that phase done) at optimiser step ``step`` of a one-cycle schedule."""
    peak = max(float(s.warmup_steps) - 1.0, 1e-9)  # the step at the peak rate (OneCycleLR's phase end)
    if step <= peak:
        return True, step / peak
    return False, (step - peak) / max(float(s.steps - 1) - peak, 1e-9)


def lr_factor(step: int, s: Any) -> float:
    """Multiplier of ``lr`` for optimiser step ``step`` (0-based): linear warm-up, then cosine or constant; or
    one cycle (``onecycle``: the warm-up is its rising phase)."""
    if s.schedule == "onecycle":
        rising, pct = _onecycle_phase(step, s)
        low = 1.0 / ONECYCLE_DIV
        return _cos_between(low, 1.0, pct) if rising else _cos_between(1.0, low / ONECYCLE_FINAL_DIV, pct)
    if s.warmup_steps and step < s.warmup_steps:
        return (step + 1) / s.warmup_steps
    if s.schedule == "constant":
        return 1.0
    span = max(1, s.steps - s.warmup_steps)
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, (step - s.warmup_steps) / span)))


def beta1(step: int, s: Any) -> float | None:
    """Adam's beta1 for optimiser step ``step``: cycled against the rate by ``onecycle``, else None (Adam's own)."""
    if s.schedule != "onecycle":
        return None
    rising, pct = _onecycle_phase(step, s)
    at_peak, at_ends = ONECYCLE_BETA1
    return _cos_between(at_ends, at_peak, pct) if rising else _cos_between(at_peak, at_ends, pct)
