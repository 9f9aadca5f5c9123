"""Adding a metric or a rotation loss touches one place: a toy per-pose metric, a toy per-trajectory metric and a
toy rotation loss, each registered by one call (registry.py), flow through the test evaluation and its CSV, the
validation of training, the config's accepted values, the report tables and their captions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from loopfakes import FakeSource, TinyNet, samples, settings
from pydantic import ValidationError

from bronchocli import geometry, metrics, odometry, registry
from bronchocli.cells import parse_only
from bronchocli.config import Config, expand_grid
from bronchocli.errors import ConfigError
from bronchocli.registry import MetricSpec, RotLossSpec
from bronchocli.reporting.aggregate import RunErrors
from bronchocli.reporting.collect import RunRecord, index_runs
from bronchocli.reporting.tables import ReportContext, personalized, tracking
from bronchocli.training import evaluate
from bronchocli.training.loop import Trainer
from bronchocli.training.network import PoseRegressor


def toy_x(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Per pose: the absolute error along x alone, voxels."""
    return (pred[..., 0] - gt[..., 0]).abs()


def toy_settled(e: odometry.TrackErrors) -> float:
    """Per trajectory: the frames whose position error is under one voxel."""
    return float((e.pos < 1.0).sum())


def toy_l1(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """A rotation loss: mean absolute wrapped angle error."""
    return geometry.wrap_deg(pred[..., 3:] - gt[..., 3:]).abs().mean(-1)


@pytest.fixture
def toys(monkeypatch):
    monkeypatch.setattr(registry, "_METRICS", dict(registry._METRICS))  # the registrations end with the test
    monkeypatch.setattr(registry, "_ROT_LOSSES", dict(registry._ROT_LOSSES))
    registry.register_metric(MetricSpec("toy_x", toy_x, "pose", "voxels", "Toy X", "vox", tables=("paper",),
                                        validation=True))
    registry.register_metric(MetricSpec("toy_settled", toy_settled, "trajectory", "frames", "Settled", "fr",
                                        higher_is_better=True, tables=("tracking",)))
    registry.register_rot_loss(RotLossSpec("l1", "MSE+L1", toy_l1))


def _predictions(seed: int, n: int = 4, frames: int = 12) -> list[evaluate.TrajectoryPrediction]:
    """Test trajectories of two patients, predicted with noise that depends on ``seed``."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        gt_rel = rng.normal(0, 1, (frames - 1, 6))
        pred_rel = gt_rel + rng.normal(0, 0.3 + 0.05 * seed, gt_rel.shape)
        gt_abs = geometry.accumulate(np.zeros(6), gt_rel, "world")
        out.append(evaluate.TrajectoryPrediction(
            key=f"p0{i % 2}/ur/{i}", patient=f"p0{i % 2}", lobe="ur", traj_id=str(i), gt_rel=gt_rel,
            pred_rel=pred_rel, gt_abs=gt_abs, pred_abs=geometry.accumulate(np.zeros(6), pred_rel, "world"),
            spacing_mm=np.array([0.5, 0.5, 0.5])))
    return out


def test_the_metrics_are_computed_logged_and_written_by_the_evaluation(toys):
    preds = _predictions(0)
    assert "toy_x" in metrics.per_pose_errors(preds[0].pred_rel, preds[0].gt_rel)
    assert set(odometry.trajectory_metrics(preds[0].pred_abs, preds[0].gt_abs)) >= {"ctf", "toy_settled"}
    logged, table = evaluate.evaluate(preds, np.zeros(6), "world")
    for key in ("pair.toy_x.mean", "acc.toy_x.std", "train_mean.pair.toy_x.mean", "traj.toy_settled.mean",
                "zero_motion.traj.toy_settled.mean", "pair.pos_l2.mean", "traj.ctf.mean"):
        assert key in logged, key
    expected = np.mean([np.abs(p.pred_rel[:, 0] - p.gt_rel[:, 0]).mean() for p in preds])
    assert table["model.pair.toy_x"].mean() == pytest.approx(expected)
    assert {"model.acc.toy_x", "train_mean.traj.toy_settled", "model.pair.pos_l2_mm"} <= set(table.columns)


def test_training_validates_the_metric_and_trains_with_the_loss(toys):
    net = PoseRegressor(TinyNet(), (0.5,) * 3, (0.25,) * 3)
    trainer = Trainer(net, samples(16), samples(8, seed=2), FakeSource(), settings(rot_loss="l1", steps=2),
                      device=torch.device("cpu"))
    values = trainer.validate()
    assert {"val.toy_x", "val.pos_l2", "val.ce", "val.ratio.pos_l2"} <= set(values)
    assert "val.geodesic" not in values  # not a validation metric
    out = torch.zeros(1, 1, 6, requires_grad=True)
    loss = metrics.pose_loss(out, torch.tensor([[[0.0, 0, 0, 10, -20, 30]]]), "l1")
    loss.backward()
    assert float(loss.detach()) == pytest.approx(20.0) and torch.isfinite(out.grad).all()


def test_the_config_accepts_the_loss_and_names_the_metric(toys):
    grid = {"arch": ["lstm"], "population": ["personalized"], "seed": [0]}
    cfg = Config.model_validate({"name": "t", "grid": grid})
    assert [c.rot_loss for c in expand_grid(cfg, ["p00"])] == ["mse", "de", "ce", "l1"]  # the default grid
    spelled = Config.model_validate({"name": "t", "grid": {**grid, "rot_loss": ["L1"]}})
    assert [c.label for c in expand_grid(spelled, ["p00"])] == ["lstm/l1/personalized/s0/world"]
    assert parse_only(["rot_loss=l1"]) == {"rot_loss": {"l1"}}
    stage = {"name": "b", "source": "a", "select": {"by": "val.toy_x"}}
    with pytest.raises(ValidationError, match=r"val_best\.ce, val_best\.toy_x or val_best\.loss"):
        Config.model_validate({"name": "t", "stages": [{"name": "a"}, stage]})


def test_without_the_registration_the_loss_is_refused():
    with pytest.raises(ConfigError, match="rot_loss 'l1': must be one of mse, de, ce$"):
        Config.model_validate({"name": "t"}).cell(arch="lstm", rot_loss="l1", population="personalized")
    with pytest.raises(ValueError, match="rotation loss 'l1' is not one of mse, de, ce"):
        metrics.pose_loss(torch.zeros(1, 6), torch.zeros(1, 6), "l1")
    assert "toy_x" not in metrics.per_pose_errors(np.zeros((1, 6)), np.zeros((1, 6)))


def _runs() -> ReportContext:
    """Runs whose metrics and trajectory_errors.csv come from the evaluation itself: lstm with CE and L1."""
    records, errors = [], {}
    for loss in ("ce", "l1"):
        for seed in (0, 1, 2):
            logged, table = evaluate.evaluate(_predictions(seed + (3 if loss == "l1" else 0)), np.zeros(6), "world")
            run_id = f"r{len(records):02d}"
            tags = {"arch": "lstm", "rot_loss": loss, "population": "personalized", "fold": "", "seed": str(seed),
                    "pose_frame": "world", "train_trajectories": "", "cell_key": f"k-{run_id}",
                    "stop_reason": "budget", "init": "random"}
            records.append(RunRecord(run_id, "FINISHED", 0, tags, logged))
            errors[run_id] = RunErrors.from_frame(table)
    return ReportContext(index_runs(records, "s", "e", None), errors=lambda run: errors.get(run.run_id))


def test_the_metrics_and_the_loss_are_in_the_report_tables(toys):
    ctx = _runs()
    t = personalized(ctx, "pair")
    assert [c.title for c in t.columns] == ["Position L2", "Rotation L2", "DE", "CE", "Toy X"]
    assert [r.label for r in t.rows if r.kind == "model"] == ["MSE+CE", "MSE+L1"]
    toy = [r.values[-1] for r in t.rows if r.kind == "model"]
    assert all(v is not None and v.mean > 0 for v in toy)
    assert t.columns[-1].heading == "Toy X (vox)" and "Toy X" not in " ".join(t.warnings)
    track = tracking(ctx, "pair")
    assert track.columns[-1].heading == "Settled (fr)"
    assert [r.label for r in track.rows if r.kind == "model"] == ["MSE+CE", "MSE+L1"]
    settled = [r.values[-1].mean for r in track.rows if r.kind == "model"]
    assert all(0 < v <= 12 for v in settled)  # frames counted, per trajectory, over the evaluation's 12
