"""The claim order of a stage's cells: the longest first, architectures of different cost side by side.

Workers claim cells in the order of the claims table's ``ord`` column, which ``plan.add_cells`` fills in the
order given here. A cell's expected cost is its budget (``train.steps`` x pairs per step) over its
architecture's measured training rate (pairs/s of the setting the speed settings file chose; ``speed.py``),
so the order is the longest-processing-time-first rule of list scheduling: the expensive cells start first and
the cheap ones fill the gaps at the end, instead of one worker idling while the last expensive cell runs alone.
Cells whose costs are within :data:`BAND` of each other are interleaved by architecture (round robin), so
two workers train different architectures side by side: on a 2-core machine two ConvLSTM cells slow each
other more than a ConvLSTM beside an OffsetNet (40-42 vs 61 pairs/s, issue 31). Without a measurement of the
architectures (no settings for this device), the grid order stays.

No torch here: the sweep's parent plans without loading it.
"""

from __future__ import annotations

from collections.abc import Sequence

from .. import speed
from ..cells import Cell
from ..config import Config

BAND = 0.2  # cells within 20 % of the most expensive cell of their band count as equally expensive


def measured_rates(cfg: Config) -> dict[str, float]:
    """Training pairs/s per architecture for the device the config trains on: a measured CUDA device when
    ``train.device`` says cuda (the first one the settings file names), else the CPU."""
    path = cfg.paths.speed_settings
    if cfg.train.device in ("cuda", "auto"):
        try:
            keys = [k for k in speed.load(path)["devices"] if k.startswith("cuda:")]
        except Exception:  # noqa: BLE001 - a bad file is reported by the run that reads it, not the planner
            keys = []
        if keys and cfg.train.device == "cuda":
            return speed.training_rates(keys[0], path)
    return speed.training_rates("cpu", path)


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
    """``cells`` in the order workers should claim them (see the module doc); stable for equal costs."""
    costs = expected_costs(cfg, cells)
    if costs is None or len(cells) < 2:
        return list(cells)
    ranked = sorted(cells, key=lambda c: -costs[c.key])  # stable: grid order among equal costs
    out: list[Cell] = []
    while ranked:
        head = costs[ranked[0].key]
        band = [c for c in ranked if costs[c.key] >= (1 - BAND) * head]
        ranked = ranked[len(band):]
        out += _interleave(band)
    return out


def _interleave(cells: list[Cell]) -> list[Cell]:
    """Round robin over the architectures of ``cells`` (each architecture's cells in their given order)."""
    queues: dict[str, list[Cell]] = {}
    for c in cells:
        queues.setdefault(c.arch, []).append(c)
    out: list[Cell] = []
    while any(queues.values()):
        for q in queues.values():
            if q:
                out.append(q.pop(0))
    return out
