"""Camera-tracking metrics (CTF, ATE, RPE, drift): hand-computed cases and the evo package as reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bronchocli import geometry as g
from bronchocli import odometry as o


def _random_walk(rng: np.random.Generator, n: int, step: float = 1.0, turn: float = 5.0) -> np.ndarray:
    """Absolute poses ``(n, 6)`` of a camera moving forward and turning a little each frame."""
    deltas = np.concatenate([rng.normal([step, 0, 0], 0.2, (n - 1, 3)), rng.normal(0, turn, (n - 1, 3))], 1)
    return g.accumulate(np.array([10.0, 20.0, 30.0, 20.0, -40.0, 70.0]), deltas, "camera")


def _noisy(rng: np.random.Generator, gt: np.ndarray, pos: float, rot: float) -> np.ndarray:
    """A tracker's chained estimate: the true relative poses plus noise, accumulated from the true first pose."""
    rel = g.relative_trajectory(gt, "camera")
    rel = rel + np.concatenate([rng.normal(0, pos, (len(rel), 3)), rng.normal(0, rot, (len(rel), 3))], 1)
    return g.accumulate(gt[0], rel, "camera")


def _evo_path(poses: np.ndarray):
    from evo.core.trajectory import PosePath3D

    mats = []
    for p in poses:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("XYZ", p[3:], degrees=True).as_matrix()
        T[:3, 3] = p[:3]
        mats.append(T)
    return PosePath3D(poses_se3=mats)


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(3)
    gt = _random_walk(rng, 40)
    return gt, _noisy(rng, gt, 0.15, 1.5)


def test_ate_is_evos_unaligned_ape_rmse(case):
    metrics = pytest.importorskip("evo.core.metrics")
    gt, pred = case
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((_evo_path(gt), _evo_path(pred)))
    assert o.trajectory_metrics(pred, gt)["ate"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse),
                                                                 rel=1e-9)


@pytest.mark.parametrize("gap", [1, 5, 10])
def test_rpe_is_evos_all_pairs_rpe_rmse(case, gap):
    metrics = pytest.importorskip("evo.core.metrics")
    gt, pred = case
    got = o.trajectory_metrics(pred, gt, thresholds=o.Thresholds(gap=gap))
    for relation, key in ((metrics.PoseRelation.translation_part, "rpe_trans"),
                          (metrics.PoseRelation.rotation_angle_deg, "rpe_rot")):
        rpe = metrics.RPE(relation, delta=gap, delta_unit=metrics.Unit.frames, all_pairs=True)
        rpe.process_data((_evo_path(gt), _evo_path(pred)))
        assert got[key] == pytest.approx(rpe.get_statistic(metrics.StatisticsType.rmse), rel=1e-7), key


def test_hand_computed_straight_line_with_a_scale_error():
    # Truth: 11 frames 1 voxel apart along x, no rotation. Estimate: 1.1 voxels per frame.
    gt = np.zeros((11, 6))
    gt[:, 0] = np.arange(11)
    pred = gt.copy()
    pred[:, 0] *= 1.1
    err = 0.1 * np.arange(11)  # position error per frame
    m = o.trajectory_metrics(pred, gt, spacing_mm=[0.5, 0.5, 0.5],
                             thresholds=o.Thresholds(position=0.55, position_mm=0.2, angle=1.0, gap=4))
    assert m["ate"] == pytest.approx(math.sqrt(np.mean(err ** 2)))
    assert m["ate_mm"] == pytest.approx(0.5 * m["ate"])
    assert m["rpe_trans"] == pytest.approx(0.4)  # every 4-frame motion is 4.4 instead of 4
    assert m["rpe_rot"] == pytest.approx(0.0, abs=1e-9)
    assert m["drift"] == pytest.approx(100 * 1.0 / 10.0)  # 1 voxel off after a 10-voxel path: 10 %
    assert m["ctf"] == pytest.approx(100 * 5 / 10)  # frames 1..5 (errors 0.1..0.5 < 0.55) of frames 1..10
    assert m["ctf_mm"] == pytest.approx(100 * 3 / 10)  # 0.05, 0.10, 0.15 mm < 0.2 mm


def test_ctf_needs_both_position_and_angle_under_their_thresholds():
    gt = np.zeros((5, 6))
    gt[:, 0] = np.arange(5)
    pred = gt.copy()
    pred[1:, 3] = [5.0, 15.0, 5.0, 15.0]  # roll errors; positions perfect
    m = o.trajectory_metrics(pred, gt, thresholds=o.Thresholds(angle=10.0))
    assert m["ctf"] == pytest.approx(50.0)
    assert m["ctf_mm"] == pytest.approx(50.0)


def test_rotation_errors_do_not_depend_on_the_euler_triple():
    rng = np.random.default_rng(4)
    gt = _random_walk(rng, 20, turn=20.0)
    pred = gt.copy()
    # the same rotations written with beta beyond 90 degrees: (a + 180, 180 - b, c + 180)
    pred[:, 3:] = np.stack([gt[:, 3] + 180.0, 180.0 - gt[:, 4], gt[:, 5] + 180.0], 1)
    m = o.trajectory_metrics(pred, gt, thresholds=o.Thresholds(gap=3))
    assert m["rpe_rot"] == pytest.approx(0.0, abs=1e-10) and m["ctf"] == 100.0 and m["ate"] == 0.0


def test_a_perfect_tracker_and_a_trajectory_too_short_for_the_gap():
    gt = _random_walk(np.random.default_rng(5), 6)
    m = o.trajectory_metrics(gt, gt, thresholds=o.Thresholds(gap=10))
    assert m["ctf"] == 100.0 and m["ate"] == 0.0 and m["drift"] == 0.0
    assert math.isnan(m["rpe_trans"]) and math.isnan(m["rpe_rot"])  # no frame pair 10 apart


@pytest.mark.parametrize("tiny", [1e-12, 1e-9, 1e-6])
def test_rpe_rotation_of_a_near_perfect_tracker_is_exact_like_the_log_map(tiny):
    """A tracker off by ``tiny`` degrees about one axis: RPE rot is that angle (the rotation log), not the
    ~6e-7° floor of arccos(trace); compared with SciPy's rotation magnitude (and evo's log map when present)."""
    gt = _random_walk(np.random.default_rng(6), 12)
    pred = gt.copy()
    R = Rotation.from_euler("XYZ", gt[:, 3:], degrees=True) * Rotation.from_rotvec([0.0, 0.0, np.radians(tiny)])
    pred[:, 3:] = R.as_euler("XYZ", degrees=True)
    _, rot = o.relative_pose_errors(pred, gt, 1)
    Rp = Rotation.from_euler("XYZ", pred[:, 3:], degrees=True)
    Rg = Rotation.from_euler("XYZ", gt[:, 3:], degrees=True)
    ref = np.degrees(((Rg[:-1].inv() * Rg[1:]).inv() * (Rp[:-1].inv() * Rp[1:])).magnitude())
    assert rot == pytest.approx(ref, rel=1e-3, abs=5e-13)  # Euler angles of ~50° hold ~1e-14° only
    assert np.all(rot < 10 * tiny + 1e-12)  # arccos of the trace gives ~6e-7 here
    lie = pytest.importorskip("evo.core.lie_algebra")
    E = [(np.linalg.inv(a) @ b) for a, b in zip(
        [np.linalg.inv(g.euler_to_matrix(x)) @ g.euler_to_matrix(y) for x, y in zip(gt[:-1, 3:], gt[1:, 3:])],
        [np.linalg.inv(g.euler_to_matrix(x)) @ g.euler_to_matrix(y) for x, y in zip(pred[:-1, 3:], pred[1:, 3:])])]
    evo_deg = np.degrees([lie.so3_log_angle(e) for e in E])
    assert rot == pytest.approx(evo_deg, rel=1e-3, abs=5e-13)


def test_rotation_angle_is_accurate_over_its_whole_range():
    rng = np.random.default_rng(7)
    rv = rng.normal(size=(5000, 3))
    rv *= (rng.uniform(0, np.pi, 5000) / np.linalg.norm(rv, axis=1))[:, None]
    rv[:10] *= 1e-10  # near 0
    rv[10:20] *= (np.pi - 1e-9) / np.linalg.norm(rv[10:20], axis=1)[:, None]  # near 180 degrees
    got = o._angle_deg(Rotation.from_rotvec(rv).as_matrix())
    assert got == pytest.approx(np.degrees(np.linalg.norm(rv, axis=1)), rel=1e-9, abs=1e-10)
