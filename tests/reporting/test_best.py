"""`track --best TABLE`: the table's network/loss row with the lowest mean headline ratio, then its best run."""

from __future__ import annotations

from collections import defaultdict

import pytest

from bronchocli.errors import BronchoError
from bronchocli.reporting.best import best_run


def _expected(golden, population: str):
    """Recomputed from the golden labels: the kept (newest FINISHED, this config's) runs of the population."""
    rows = defaultdict(list)
    for label, run_id in golden.ids.items():
        parts = label.split("/")
        if parts[0] != population or label.endswith(("-old", "-failed")):
            continue
        m = golden.client.get_run(run_id).data.metrics
        rows[(parts[1], parts[2])].append((m["pair.pos_l2.mean"] / m["train_mean.pair.pos_l2.mean"], run_id))
    means = {k: sum(r for r, _ in v) / len(v) for k, v in rows.items()}
    row = min(means, key=means.get)
    return row, means[row], min(rows[row])[1]


@pytest.mark.parametrize("table", ["personalized", "cross-subject"])
def test_best_run_is_the_best_rows_best_run_by_the_headline_ratio(golden_store, table):
    row, mean, run_id = _expected(golden_store, table)
    best = best_run(golden_store.client, golden_store.cfg, table)
    assert best.row == row and best.row_ratio == pytest.approx(mean) and best.run.run_id == run_id
    assert run_id in best.describe() and f"{row[0]}/{row[1]}" in best.describe()


def test_an_unknown_table_is_one_line(golden_store):
    with pytest.raises(BronchoError, match="--best 'ablation': must be one of personalized, cross-subject"):
        best_run(golden_store.client, golden_store.cfg, "ablation")
