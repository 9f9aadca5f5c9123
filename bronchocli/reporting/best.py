"""The best run of a report table, by the report's headline figure (what ``track --best TABLE`` applies).

The headline figure is the one the README quotes (``runkeys.HEADLINE``): the
per-pair position error divided by the training-mean reference's on the same
test trajectories (``runkeys.headline``; below 1 = better than predicting the
training set's mean motion for every pair). Among the table's
runs (the config's cells of that table's population, pose frame and training
size, one FINISHED run per cell, as ``report`` keeps them) the network/loss
row with the lowest mean ratio over its runs wins, and within it the run with
the lowest ratio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .. import runkeys
from ..config import Config
from ..errors import BronchoError
from .collect import ARCH, FRAME, LOSS, POP, SIZE, RunRecord
from .report import collect_index

TABLE_POPULATIONS = {"personalized": "personalized", "cross-subject": "cross-subject"}


@dataclass(frozen=True)
class BestRun:
    run: RunRecord
    table: str
    row: tuple[str, str]  # (arch, rot_loss)
    row_ratio: float  # mean headline ratio of the row's runs
    row_runs: int
    ratio: float  # the chosen run's

    def describe(self) -> str:
        arch, loss = self.row
        return (f"best of table {self.table}: {arch}/{loss} (pair position error / training-mean reference "
                f"{self.row_ratio:.3f}, mean of {self.row_runs} run(s)); run {self.run.run_id} "
                f"({self.run.label}, {self.ratio:.3f})")


def best_run(client, cfg: Config, table: str) -> BestRun:
    """The table's best run (module doc); BronchoError (one line) when the table is unknown or has no run."""
    if table not in TABLE_POPULATIONS:
        raise BronchoError(f"--best {table!r}: must be one of {', '.join(TABLE_POPULATIONS)} (a table whose rows are "
                           "network/loss combinations)")
    index = collect_index(client, cfg)
    population = TABLE_POPULATIONS[table]
    rows: dict[tuple[str, str], list[tuple[float, RunRecord]]] = {}
    for ident, run in index.runs.items():
        if ident[POP] != population or ident[FRAME] != index.pose_frame or ident[SIZE] != index.train_size:
            continue
        ratio = runkeys.headline(run.metrics)
        if math.isfinite(ratio):
            rows.setdefault((ident[ARCH], ident[LOSS]), []).append((ratio, run))
    if not rows:
        raise BronchoError(f"--best {table}: no FINISHED {population} run of config {cfg.name!r} in "
                           f"experiment {cfg.experiment_name!r} (run the sweep first, or give --run)")
    means = {row: sum(r for r, _ in runs) / len(runs) for row, runs in rows.items()}
    row = min(means, key=lambda k: (means[k], k))
    ratio, run = min(rows[row], key=lambda rr: (rr[0], rr[1].run_id))
    return BestRun(run, table, row, means[row], len(rows[row]), ratio)
