"""End to end on CPU: every architecture x rotation loss lands one FINISHED MLflow run with every metric."""

from __future__ import annotations

import pandas as pd
import pytest

from bronchocli import tracking
from bronchocli.config import ARCHS, ROT_LOSSES, make_cell
from bronchocli.training.run import run_cell

METRIC_NAMES = ("pos_l2", "pos_l2_mm", "rot_l2", "de", "ce", "geodesic")
EXPECTED = (
    [f"{scope}.{m}.{s}" for scope in ("pair", "acc") for m in METRIC_NAMES for s in ("mean", "std")]
    + [f"traj.{m}.{s}" for m in ("ate", "ate_mm", "rpe_trans", "rpe_rot") for s in ("mean", "std")]
    + ["test.n_pairs", "test.n_trajectories", "n_params", "train.pairs_per_s", "best_val_loss",
       "zero_motion.pair.pos_l2.mean"]
)


def artifacts(client, run_id: str, path: str = "") -> set[str]:
    out = set()
    for f in client.list_artifacts(run_id, path or None):
        out |= artifacts(client, run_id, f.path) if f.is_dir else {f.path}
    return out


@pytest.mark.parametrize("rot_loss", ROT_LOSSES)
@pytest.mark.parametrize("arch", ARCHS)
def test_every_arch_and_loss_lands_a_finished_run(tiny_cfg, arch, rot_loss):
    cell = make_cell(tiny_cfg, arch, rot_loss, "personalized", None, 0, "world")
    result = run_cell(tiny_cfg, cell, progress=False)
    assert result.status == "FINISHED", result.failure_reason
    client = tracking.client_for(tiny_cfg)
    run = client.get_run(result.run_id)
    assert run.info.status == "FINISHED"
    missing = [m for m in EXPECTED if m not in run.data.metrics]
    assert not missing, missing
    tags = run.data.tags
    assert (tags["arch"], tags["rot_loss"], tags["population"], tags["fold"]) == (arch, rot_loss, "personalized", "")
    assert tags["cell_key"] == cell.key and tags["sweep"] == "tiny" and len(tags["dataset_fingerprint"]) == 64
    assert tags["pose_frame"] == "world" and tags["seed"] == "0" and tags["bronchocli_version"]
    assert run.data.params["train.lr"] == "0.0001" and run.data.params["grid.arch"]
    history = client.get_metric_history(result.run_id, "val_loss")
    assert len(history) == 1 and history[0].step == 0
    files = artifacts(client, result.run_id)
    assert {"config.yaml", "split_manifest.csv", "predictions.csv", "trajectories.png"} <= files
    table = pd.read_csv(client.download_artifacts(result.run_id, "predictions.csv"))
    # 2 patients x 2 lobes x 1 test trajectory of 8 frames
    assert len(table) == 2 * 2 * 8 and run.data.metrics["test.n_pairs"] == 2 * 2 * 7
    first = table[table.frame == 0]
    assert first.filter(like="pred_rel_").isna().all().all()
    assert (first.filter(like="pred_abs_").values == first.filter(like="gt_abs_").values).all()
