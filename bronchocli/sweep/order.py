"""The claim order of a stage's cells: the longest first, architectures of different cost side by side.

Workers claim cells in the order of the claims table's ``ord`` column, which ``plan.add_cells`` fills in the
order given here. A cell's expected cost is its budget (``train.steps`` x pairs per step) over its
architecture's measured training rate (pairs/s of the setting the speed settings file chose; ``speed.py``),
so the order is the longest-processing-time-first rule of list scheduling: the expensive cells start first and
the cheap ones fill the gaps at the end, instead of one worker idling while the last expensive cell runs alone.
Consecutive cells alternate architectures where that costs little (the next one is of another architecture
when it costs at least :data:`ALTERNATE` of the costliest cell left), so two workers train different
architectures side by side: on a 2-core machine two ConvLSTM cells slow each other more than a ConvLSTM
beside an OffsetNet (40-42 vs 61 pairs/s, issue 31). ``benchmarks/bench_claims.py`` simulates both effects.
Without a measurement of the architectures (no settings for this device), the grid order stays.

No torch here: the sweep's parent plans without loading it.
"""

from __future__ import annotations

from collections.abc import Sequence

from .. import speed
from ..cells import Cell
from ..config import Config

ALTERNATE = 0.5  # the next cell is of another architecture when it costs at least half the costliest left


def measured_rates(cfg: Config) -> dict[str, float]:
    """Training pairs/s per architecture for the device the config trains on: a measured CUDA device when
    ``train.device`` says cuda (the first one the settings file names), else this CPU (``speed.cpu_key``)."""
    path = cfg.paths.speed_settings
    if cfg.train.device in ("cuda", "auto"):
        try:
            keys = [k for k in speed.load(path)["devices"] if k.startswith("cuda:")]
        except Exception:  # noqa: BLE001 - a bad file is reported by the run that reads it, not the planner
            keys = []
        if keys and cfg.train.device == "cuda":
            return speed.training_rates(keys[0], path)
    return speed.training_rates(speed.cpu_key(), path)


def expected_costs(cfg: Config, cells: Sequence[Cell]) -> dict[str, float] | None:
    """Expected seconds of training per cell key, or None when no architecture of ``cells`` was measured."""
    rates = measured_rates(cfg)
    known = [rates[c.arch] for c in cells if c.arch in rates]
    if not known:
        return None
    fallback = sorted(known)[len(known) // 2]  # an unmeasured architecture: the median measured rate
    pairs = cfg.train.steps * cfg.train.pairs_per_step
    return {c.key: pairs / rates.get(c.arch, fallback) for c in cells}


def claim_order(cfg: Config, cells: Sequence[Cell]) -> list[Cell]:
    """``cells`` in the order workers should claim them (see the module doc); the grid order among equals."""
    costs = expected_costs(cfg, cells)
    if costs is None or len(cells) < 2:
        return list(cells)
    left = sorted(cells, key=lambda c: -costs[c.key])  # stable: grid order among equal costs
    out: list[Cell] = []
    while left:
        pick = left[0]
        if out:  # the cell claimed next runs beside the one just ordered: another architecture if one is near
            other = next((c for c in left if c.arch != out[-1].arch), None)
            if other is not None and costs[other.key] >= ALTERNATE * costs[pick.key]:
                pick = other
        out.append(pick)
        left.remove(pick)
    return out
