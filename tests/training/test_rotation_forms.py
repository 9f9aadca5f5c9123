"""Rotation errors compare rotations, not Euler triples: the same rotations written in either XYZ form score alike.

Every rotation R = Rx(a) Ry(b) Rz(c) is also Rx(a+180) Ry(180-b) Rz(c+180). Chaining always returns the canonical
triple (b in [-90, 90]); a ground truth written in the other form used to be compared triple against triple
(issue 23: accumulated rotation L2 272°, CE 1.70 for a perfect predictor, with DE and geodesic 0).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bronchocli import geometry
from bronchocli.training import evaluate

ROTATION_METRICS = ("rot_l2", "de", "ce", "geodesic")


def other_form(poses: np.ndarray) -> np.ndarray:
    """The same poses with every rotation written as (a+180, 180-b, c+180), wrapped: b lies outside [-90, 90]."""
    out = poses.copy()
    a, b, c = poses[:, 3], poses[:, 4], poses[:, 5]
    out[:, 3:] = geometry.wrap_deg(np.column_stack([a + 180.0, 180.0 - b, c + 180.0]))
    return out


def trajectory(n: int = 30, seed: int = 0) -> np.ndarray:
    """A smooth canonical camera path whose pitch stays within ±60°."""
    rng = np.random.default_rng(seed)
    pos = np.cumsum(rng.normal(0, 1, (n, 3)), 0) + 50.0
    ang = np.array([20.0, 40.0, -30.0]) + np.cumsum(rng.normal(0, 3, (n, 3)), 0)
    ang[:, 1] = np.clip(ang[:, 1], -60, 60)
    return np.column_stack([pos, geometry.wrap_deg(ang)])


def perfect(gt_abs: np.ndarray, frame: str) -> evaluate.TrajectoryPrediction:
    """A predictor that outputs the true relative poses, chained from the true first pose."""
    rel = geometry.relative_trajectory(gt_abs, frame)
    return evaluate.TrajectoryPrediction(
        key="p00/ur/0", patient="p00", lobe="ur", traj_id="0", gt_rel=rel, pred_rel=rel.copy(), gt_abs=gt_abs,
        pred_abs=geometry.accumulate(gt_abs[0], rel, frame), spacing_mm=np.array([0.5, 0.5, 0.5]), frame=frame)


def test_the_other_form_is_the_same_rotation_with_beta_beyond_90():
    poses = trajectory()
    flipped = other_form(poses)
    assert (np.abs(flipped[:, 4]) > 90).all()
    same = Rotation.from_euler("XYZ", flipped[:, 3:], degrees=True).inv() * \
        Rotation.from_euler("XYZ", poses[:, 3:], degrees=True)
    assert np.degrees(same.magnitude()).max() < 1e-9


@pytest.mark.parametrize("frame", ["camera", "world"])
def test_perfect_predictor_on_the_other_form_scores_zero_rotation_error(frame):
    """The issue's reproduction: every rotation metric, per pair and accumulated, is 0."""
    gt_abs = other_form(trajectory())
    pred = perfect(gt_abs, frame)
    out = evaluate.score([pred])
    for evaluation in ("pair", "acc"):
        for m in ROTATION_METRICS:
            assert out[f"{evaluation}.{m}.mean"] == pytest.approx(0.0, abs=1e-5), (evaluation, m)  # arccos near 1: ~1e-6°
    table = evaluate.trajectory_table([pred], {})
    for m in ROTATION_METRICS:
        assert table[f"model.acc.{m}"].abs().max() < 1e-5, m


def test_accumulated_errors_do_not_depend_on_the_written_form():
    """A noisy camera-frame predictor scores the same against either form of the same ground truth."""
    poses = trajectory(seed=3)
    rng = np.random.default_rng(5)
    rel = geometry.relative_trajectory(poses, "camera")
    noisy = rel + np.concatenate([rng.normal(0, 0.3, rel[:, :3].shape), rng.normal(0, 2.0, rel[:, 3:].shape)], 1)
    scores = []
    for gt_abs in (poses, other_form(poses)):
        gt_rel = geometry.relative_trajectory(gt_abs, "camera")
        p = evaluate.TrajectoryPrediction(
            key="p00/ur/0", patient="p00", lobe="ur", traj_id="0", gt_rel=gt_rel, pred_rel=noisy, gt_abs=gt_abs,
            pred_abs=geometry.accumulate(gt_abs[0], noisy, "camera"), spacing_mm=np.ones(3), frame="camera")
        scores.append(evaluate.score([p]))
    assert scores[0]["acc.rot_l2.mean"] > 1.0  # the errors are real, not trivially zero
    for k in scores[0]:
        assert scores[1][k] == pytest.approx(scores[0][k], rel=1e-9, abs=1e-9), k


def test_camera_frame_prediction_in_the_other_form_is_not_an_error():
    """Per pair in the camera frame the delta is a rotation: a predicted triple written in its other form is right."""
    poses = trajectory(seed=4)
    pred = perfect(poses, "camera")
    written = other_form(np.column_stack([np.zeros((len(pred.pred_rel), 3)), pred.pred_rel[:, 3:]]))[:, 3:]
    pred = evaluate.TrajectoryPrediction(**{**pred.__dict__, "pred_rel": np.column_stack([pred.pred_rel[:, :3],
                                                                                         written])})
    out = evaluate.score([pred])
    for m in ROTATION_METRICS:
        assert out[f"pair.{m}.mean"] == pytest.approx(0.0, abs=1e-5), m
