"""End to end on CPU: a cell lands one FINISHED MLflow run with every metric, both references and its budget."""

from __future__ import annotations

import math
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
import torch
from run_metrics import EVAL_PARAMS, EXPECTED
from scipy.spatial.transform import Rotation

from bronchocli.config import load_config
from bronchocli.inference.loading import resolve
from bronchocli.registry import arch_names, rot_loss_names
from bronchocli.runs.client import client_for
from bronchocli.training.network import load_exported
from bronchocli.training.run import run_cell

# Every architecture once and every loss at least once in CI; the full grid is `slow`.
QUICK = [("baseline", "mse"), ("lstm", "de"), ("convlstm", "ce"), ("conv3d", "mse"), ("offsetnet", "de")]
FULL = [(a, lo) for a in arch_names() for lo in rot_loss_names() if (a, lo) not in QUICK]


def artifacts(client, run_id: str, path: str = "") -> set[str]:
    out = set()
    for f in client.list_artifacts(run_id, path or None):
        out |= artifacts(client, run_id, f.path) if f.is_dir else {f.path}
    return out


def _check_cell(cfg, arch: str, rot_loss: str) -> None:
    cell = cfg.cell(arch=arch, rot_loss=rot_loss, population="personalized")
    result = run_cell(cfg, cell, progress=False)
    assert result.status == "FINISHED", result.failure_reason
    client = client_for(cfg)
    run = client.get_run(result.run_id)
    assert run.info.status == "FINISHED"
    missing = [m for m in EXPECTED if m not in run.data.metrics]
    assert not missing, missing
    m = run.data.metrics
    # The budget: 4 optimiser steps of 6 image pairs each, whatever the architecture (pairwise models: 6 pairs;
    # temporal ones: 2 windows of 3).
    assert m["train.steps"] == 4 and m["train.pairs_seen"] == 24 and run.data.tags["stop_reason"] == "budget"
    # BatchNorm statistics are re-estimated before testing: eval-mode outputs must not collapse to a constant.
    assert m["pred.std.pos"] > 1e-4 and m["pred.std.rot"] > 1e-4, m
    tags = run.data.tags
    assert (tags["arch"], tags["rot_loss"], tags["population"], tags.get("fold")) == (arch, rot_loss, "personalized",
                                                                                       None)
    assert tags["cell_key"] == cell.key and tags["sweep"] == "tiny" and len(tags["dataset_fingerprint"]) == 64
    assert tags["pose_frame"] == "world" and tags["seed"] == "0" and tags["bronchocli_version"]
    params = run.data.params  # what tells runs apart: coordinates and settings off the defaults, not the grid
    assert (params["arch"], params["rot_loss"], params["seed"], params["train.steps"]) == (arch, rot_loss, "0", "4")
    assert "grid.arch" not in params and "fold" not in params
    # the evaluation's constants: params at their defaults too, not metrics (issue 36)
    assert {k: params.get(k) for k in EVAL_PARAMS} == {"eval.ctf_position": "5.0", "eval.ctf_position_mm": "5.0",
                                                        "eval.ctf_angle": "10.0", "eval.rpe_gap": "10"}
    assert not [k for k in EVAL_PARAMS if k in m]
    history = client.get_metric_history(result.run_id, "val_loss")
    assert sorted(h.step for h in history) == [2, 4]  # step = optimiser step of each validation
    files = artifacts(client, result.run_id)
    assert {"config.yaml", "split_manifest.csv", "predictions.csv", "trajectory_errors.csv",
            "trajectories.png"} <= files
    assert not any(f.startswith("model/") for f in files)  # runs.model_artifact: none
    table = pd.read_csv(client.download_artifacts(result.run_id, "predictions.csv"))
    # 2 patients x 2 lobes x 1 test trajectory of 8 frames
    assert len(table) == 2 * 2 * 8 and m["test.n_pairs"] == 2 * 2 * 7
    first = table[table.frame == 0]
    assert first.filter(like="pred_rel_").isna().all().all()
    assert (first.filter(like="pred_abs_").values == first.filter(like="gt_abs_").values).all()
    assert not (cfg.paths.checkpoints / result.run_id).exists()  # resumable state removed once FINISHED


@pytest.mark.parametrize("arch, rot_loss", QUICK)
def test_every_arch_lands_a_finished_run_with_every_metric(tiny_cfg, arch, rot_loss):
    _check_cell(tiny_cfg, arch, rot_loss)


@pytest.mark.slow
@pytest.mark.parametrize("arch, rot_loss", FULL)
def test_every_arch_and_loss_lands_a_finished_run_with_every_metric(tiny_cfg, arch, rot_loss):
    _check_cell(tiny_cfg, arch, rot_loss)


def _world_deltas(frames: pd.DataFrame) -> np.ndarray:
    """World-frame relative poses of every trajectory, straight from the dataset CSVs (the paper's differences)."""
    out = []
    for _, t in frames.sort_values("frame").groupby(["patient", "lobe", "trajectory"]):
        d = np.diff(t[["pos_x", "pos_y", "pos_z", "Rx", "Ry", "Rz"]].to_numpy(float), axis=0)
        d[:, 3:] = (d[:, 3:] + 180.0) % 360.0 - 180.0
        out.append(d)
    return np.concatenate(out)


def test_references_and_per_trajectory_errors_match_an_independent_computation(tiny_project, tiny_cfg):
    result = run_cell(tiny_cfg, tiny_cfg.cell(arch="baseline", rot_loss="mse", population="personalized", seed=1),
                      progress=False)
    assert result.status == "FINISHED", result.failure_reason
    client = client_for(tiny_cfg)
    manifest = pd.read_csv(client.download_artifacts(result.run_id, "split_manifest.csv"), dtype=str)
    csvs = pd.concat([pd.read_csv(p, dtype={"patient": str, "lobe": str, "trajectory": str})
                      for p in sorted((tiny_project / "tiny").glob("p*.csv"))])
    keyed = csvs.merge(manifest, on=["patient", "lobe", "trajectory"])
    train_mean = _world_deltas(keyed[keyed.split == "train"]).mean(0)
    test = _world_deltas(keyed[keyed.split == "test"])
    m = result.metrics
    assert m["train_mean.pair.pos_l2.mean"] == pytest.approx(np.linalg.norm(test[:, :3] - train_mean[:3], axis=1).mean(),
                                                             rel=1e-6)
    assert m["zero_motion.pair.pos_l2.mean"] == pytest.approx(np.linalg.norm(test[:, :3], axis=1).mean(), rel=1e-6)
    assert m["zero_motion.pair.rot_l2.mean"] == pytest.approx(np.linalg.norm(test[:, 3:], axis=1).mean(), rel=1e-6)
    errors = pd.read_csv(client.download_artifacts(result.run_id, "trajectory_errors.csv"))
    assert len(errors) == m["test.n_trajectories"]
    for source, prefix in (("model", ""), ("train_mean", "train_mean."), ("zero_motion", "zero_motion.")):
        weighted = (errors[f"{source}.pair.pos_l2"] * errors.n_pairs).sum() / errors.n_pairs.sum()
        assert weighted == pytest.approx(m[f"{prefix}pair.pos_l2.mean"], rel=1e-6)
        assert errors[f"{source}.acc.pos_l2"].mean() == pytest.approx(m[f"{prefix}acc.pos_l2.mean"], rel=1e-6)
        for t in ("ctf", "ate", "drift"):
            assert errors[f"{source}.traj.{t}"].mean() == pytest.approx(m[f"{prefix}traj.{t}.mean"], rel=1e-6)


def _zero_motion_odometry(t: pd.DataFrame, gap: int, position: float, angle: float) -> dict[str, float]:
    """Camera-tracking metrics of the zero-motion reference (it never leaves the first pose), from the CSV alone."""
    p = t[["pos_x", "pos_y", "pos_z"]].to_numpy(float)
    R = Rotation.from_euler("XYZ", t[["Rx", "Ry", "Rz"]].to_numpy(float), degrees=True)
    pos_err = np.linalg.norm(p - p[0], axis=1)
    rot_err = np.degrees((R[0].inv() * R).magnitude())
    trans = np.linalg.norm(p[gap:] - p[:-gap], axis=1)  # the true motion is all error
    rot = np.degrees((R[:-gap].inv() * R[gap:]).magnitude())
    return {"ate": math.sqrt(np.mean(pos_err ** 2)),
            "drift": 100 * pos_err[-1] / np.linalg.norm(np.diff(p, axis=0), axis=1).sum(),
            "ctf": 100 * np.mean((pos_err[1:] < position) & (rot_err[1:] < angle)),
            "rpe_trans": math.sqrt(np.mean(trans ** 2)), "rpe_rot": math.sqrt(np.mean(rot ** 2))}


def test_camera_tracking_metrics_of_the_zero_motion_reference_match_the_dataset(tiny_project, tiny_cfg):
    cfg = tiny_cfg.with_values({"eval.rpe_gap": 3, "eval.ctf_position": 1.5, "eval.ctf_angle": 4.0})
    result = run_cell(cfg, cfg.cell(arch="baseline", rot_loss="mse", population="personalized", seed=2),
                      progress=False)
    assert result.status == "FINISHED", result.failure_reason
    client = client_for(cfg)
    errors = pd.read_csv(client.download_artifacts(result.run_id, "trajectory_errors.csv"),
                         dtype={"patient": str, "lobe": str, "trajectory": str})
    csvs = pd.concat([pd.read_csv(p, dtype={"patient": str, "lobe": str, "trajectory": str})
                      for p in sorted((tiny_project / "tiny").glob("p*.csv"))])
    params = client.get_run(result.run_id).data.params  # the thresholds it used: params (issue 36)
    assert params["eval.rpe_gap"] == "3" and params["eval.ctf_angle"] == "4.0" and params["eval.ctf_position"] == "1.5"
    assert "eval.rpe_gap" not in result.metrics
    for _, row in errors.iterrows():
        t = csvs[(csvs.patient == row.patient) & (csvs.lobe == row.lobe) & (csvs.trajectory == row.trajectory)]
        want = _zero_motion_odometry(t.sort_values("frame"), 3, 1.5, 4.0)
        for k, v in want.items():
            assert row[f"zero_motion.traj.{k}"] == pytest.approx(v, rel=1e-6, abs=1e-9), k


def test_the_model_artifact_is_fp16_and_predicts_like_the_trained_network(tiny_cfg):
    cfg = tiny_cfg.with_values({"runs.model_artifact": "fp16"})
    result = run_cell(cfg, cfg.cell(arch="baseline", rot_loss="ce", population="personalized", seed=3),
                      progress=False)
    assert result.status == "FINISHED", result.failure_reason
    client = client_for(cfg)
    local = Path(mlflow.artifacts.download_artifacts(resolve(client, result.run_id).location))  # its MLflow Model
    payload = torch.load(local / "data" / "bronchopose" / "weights.pt", weights_only=True)
    assert payload["arch"] == "baseline" and payload["image_size"] == 32
    assert {v.dtype for v in payload["state_dict"].values() if v.is_floating_point()} == {torch.float16}
    net = load_exported(payload)
    frames = torch.randint(0, 256, (1, 5, 3, 32, 32), dtype=torch.uint8)
    with torch.no_grad():
        pred, _ = net(frames)
    assert pred.shape == (1, 4, 6) and torch.isfinite(pred).all()


def test_budget_fields_reject_a_batch_that_does_not_hold_whole_windows(tiny_cfg):
    from bronchocli.errors import ConfigError

    cfg = tiny_cfg.with_values({"train.batch_size": 4})  # windows of 3 pairs
    with pytest.raises(ConfigError, match="must be a multiple of 3"):
        run_cell(cfg, cfg.cell(arch="convlstm", rot_loss="ce", population="personalized"), progress=False)


def test_config_rejects_an_effective_batch_that_is_not_whole_micro_batches(tiny_project):
    from bronchocli.errors import ConfigError

    with pytest.raises(ConfigError, match="effective_batch"):
        load_config(tiny_project / "experiments.yaml", overrides=["train.effective_batch=10"])
