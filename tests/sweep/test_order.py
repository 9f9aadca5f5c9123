"""The claim order: the longest cells first, architectures of similar cost interleaved (sweep/order.py)."""

from __future__ import annotations

from bronchocli import speed
from bronchocli.config import Config, expand_grid
from bronchocli.sweep import SweepStore
from bronchocli.sweep.order import claim_order
from bronchocli.sweep.plan import add_cells


def _cfg(tmp_path, rates: dict[str, float], grid: dict):
    path = tmp_path / "speed.json"
    speed.write(path, "cpu", {"measured": {}, "archs": {
        a: {"precision": "32", "channels_last": True, "chosen": "fp32 CL", "pairs_per_s": {"fp32 CL": r}}
        for a, r in rates.items()}})
    return Config.model_validate({"name": "t", "grid": grid, "train": {"device": "cpu",
                                                                     "speed_settings": str(path)}})


def _makespan_and_idle(order, cost, workers=2):
    """List scheduling as the claims table does it: each free worker takes the next cell."""
    free = [0.0] * workers
    for c in order:
        w = free.index(min(free))
        free[w] += cost[c.arch]
    return max(free), sum(max(free) - f for f in free)


def test_the_longest_cells_start_first_and_architectures_alternate(tmp_path):
    cfg = _cfg(tmp_path, {"convlstm": 60.0, "offsetnet": 20.0, "baseline": 58.0},
               {"arch": ["convlstm", "baseline", "offsetnet"], "rot_loss": ["mse"], "population": ["personalized"], "seed": [0, 1]})
    cells = expand_grid(cfg)
    order = [c.arch for c in claim_order(cfg, cells)]
    assert order[:2] == ["offsetnet", "offsetnet"]  # 3x the cost of the others: first, whatever the grid says
    assert order[2:] == ["baseline", "convlstm", "baseline", "convlstm"]  # close in cost: alternating, dearer first


def test_claim_order_beats_grid_order_on_idle_time(tmp_path):
    rates = {"convlstm": 60.0, "offsetnet": 25.0}
    cfg = _cfg(tmp_path, rates, {"arch": ["convlstm", "offsetnet"], "rot_loss": ["mse"], "population": ["personalized"], "seed": [0, 1, 2]})
    cells = expand_grid(cfg)
    cost = {a: 1 / r for a, r in rates.items()}
    before = _makespan_and_idle(cells, cost)
    after = _makespan_and_idle(claim_order(cfg, cells), cost)
    assert after[0] < before[0] and after[1] < before[1]


def test_without_a_measurement_the_grid_order_stays(tmp_path):
    cfg = _cfg(tmp_path, {}, {"arch": ["convlstm", "offsetnet"], "rot_loss": ["mse"], "population": ["personalized"], "seed": [0, 1]})
    cells = expand_grid(cfg)
    assert claim_order(cfg, cells) == cells


def test_the_claims_table_hands_cells_out_in_claim_order(tmp_path):
    cfg = _cfg(tmp_path, {"convlstm": 60.0, "offsetnet": 20.0},
               {"arch": ["convlstm", "offsetnet"], "rot_loss": ["mse"], "population": ["personalized"], "seed": [0, 1]})
    store = SweepStore(f"sqlite:///{tmp_path}/sweep.db")
    store.ensure_schema()
    cells = expand_grid(cfg)
    add_cells(cfg, store, cells)
    claimed = []
    while (claim := store.claim("t", [c.key for c in cells], "w", max_retries=0, stale_after_s=60)) is not None:
        claimed.append(claim.row.label.split("/")[0])
    assert [a[:9] for a in claimed][:2] == ["offsetnet", "offsetnet"]


def test_architectures_alternate_when_the_other_costs_at_least_half(tmp_path):
    rates = {"convlstm": 60.0, "offsetnet": 40.0}  # OffsetNet 1.5x the cost: the two run side by side
    cfg = _cfg(tmp_path, rates, {"arch": ["convlstm", "offsetnet"], "rot_loss": ["mse"],
                                 "population": ["personalized"], "seed": [0, 1, 2]})
    assert [c.arch[0] for c in claim_order(cfg, expand_grid(cfg))] == list("ocococ")
