"""Camera-tracking metrics of the literature, per trajectory: CTF, ATE, RPE over a frame gap, drift.

The bronchoscopy literature (the paper's Table 1) scores a tracker by the
share of correctly tracked frames; visual-odometry benchmarks (TUM RGB-D,
KITTI) by absolute and relative trajectory errors. Here, for one trajectory of
predicted absolute poses ``pred (N, 6)`` chained from the true first pose and
its ground truth ``gt (N, 6)`` (geometry.py conventions: voxels, XYZ Euler
degrees):

* ``ctf``: share of frames 1..N-1 whose position error is below
  ``Thresholds.position`` voxels AND whose rotation error (the geodesic angle
  of R_pred^T R_gt, so any Euler triple of a rotation scores the same) is below
  ``Thresholds.angle`` degrees; ``ctf_mm`` the same with the position error in
  mm (the dataset's voxel spacing) under ``Thresholds.position_mm``. Frame 0
  is given, so it does not count. Higher is better;
* ``ate`` / ``ate_mm``: absolute trajectory error, the RMSE over all N frames
  of the position error, no alignment (the first pose is known; evo's APE
  with ``align=False``, translation part);
* ``rpe_trans`` / ``rpe_rot``: relative pose error over a fixed gap of
  ``Thresholds.gap`` frames (TUM): for every i, E_i = (Q_i^-1 Q_i+gap)^-1
  (P_i^-1 P_i+gap) in SE(3), the RMSE over i of |t(E_i)| (voxels) and of the
  angle of R(E_i) (degrees; the norm of the rotation log, exact near 0). NaN when the trajectory has no frame pair that
  far apart;
* ``drift``: the final position error as a percentage of the ground-truth path
  length (sum of the distances between consecutive true positions).

Each metric is a function of :class:`TrackErrors` (the per-frame and
relative-pose errors of one trajectory, computed once) registered in
registry.py with its unit, label and direction; :func:`trajectory_metrics`
applies every registered one. The names avoid ``tracking``: in this project
that word means MLflow run tracking (the ``runs`` package).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import geometry, registry


@dataclass(frozen=True)
class Thresholds:
    """CTF thresholds and the RPE gap (the ``eval:`` section of the config)."""

    position: float = 5.0  # voxels
    position_mm: float = 5.0  # mm, for ctf_mm
    angle: float = 10.0  # degrees, geodesic
    gap: int = 10  # frames between the two poses of a relative pose error


def _rotations(poses: np.ndarray) -> np.ndarray:
    return geometry.euler_to_matrix(poses[:, 3:])


def _angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle of each ``(..., 3, 3)`` matrix in degrees: the norm of the rotation log, in its atan2
    form ``atan2(|vee(R - R^T)|, trace(R) - 1)`` (sin and cos of the angle, each times 2). Unlike arccos of the
    trace, which floors at ~6e-7° (the cosine of a tiny angle rounds to 1), it is exact near 0, as evo's
    log map is, and accurate up to 180°; never NaN."""
    vee = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.degrees(np.arctan2(np.linalg.norm(vee, axis=-1), np.trace(R, axis1=-2, axis2=-1) - 1.0))


def frame_errors(pred, gt, spacing_mm=None) -> dict[str, np.ndarray]:
    """Per frame: position error in voxels (``pos``), in mm (``pos_mm``) and geodesic rotation error (``rot``)."""
    pred, gt = np.asarray(pred, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    diff = pred[:, :3] - gt[:, :3]
    scale = np.ones(3) if spacing_mm is None else np.asarray(spacing_mm, dtype=np.float64)
    R_err = np.swapaxes(_rotations(pred), -1, -2) @ _rotations(gt)
    return {"pos": np.linalg.norm(diff, axis=1), "pos_mm": np.linalg.norm(diff * scale, axis=1),
            "rot": _angle_deg(R_err)}


def _rmse(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x * x))) if x.size else math.nan


def relative_pose_errors(pred, gt, gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Translation (voxels) and rotation (degrees) of E_i = (Q_i^-1 Q_i+gap)^-1 (P_i^-1 P_i+gap) for every i."""
    pred, gt = np.asarray(pred, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    n = len(gt)
    if gap < 1 or n <= gap:
        return np.empty(0), np.empty(0)
    Rp, Rq = _rotations(pred), _rotations(gt)

    def motion(R, p):  # relative motion from frame i to i + gap, in frame i: (R_i^T R_j, R_i^T (p_j - p_i))
        Ri_T = np.swapaxes(R[:-gap], -1, -2)
        return Ri_T @ R[gap:], np.einsum("nij,nj->ni", Ri_T, p[gap:, :3] - p[:-gap, :3])

    dRp, dtp = motion(Rp, pred)
    dRq, dtq = motion(Rq, gt)
    dRq_T = np.swapaxes(dRq, -1, -2)
    trans = np.einsum("nij,nj->ni", dRq_T, dtp - dtq)  # translation of inv(D_gt) D_pred
    return np.linalg.norm(trans, axis=1), _angle_deg(dRq_T @ dRp)


def path_length(gt) -> float:
    gt = np.asarray(gt, dtype=np.float64)
    return float(np.linalg.norm(np.diff(gt[:, :3], axis=0), axis=1).sum())


@dataclass(frozen=True)
class TrackErrors:
    """One trajectory's errors, what every per-trajectory metric is computed from (:func:`track_errors`)."""

    pos: np.ndarray  # (N,) position error per frame, voxels
    pos_mm: np.ndarray  # (N,) the same in mm (voxels where the spacing is unknown)
    rot: np.ndarray  # (N,) geodesic rotation error per frame, degrees
    rpe_trans: np.ndarray  # relative pose errors over the gap: translation (voxels) ...
    rpe_rot: np.ndarray  # ... and rotation (degrees); empty when the trajectory is shorter than the gap
    length: float  # ground-truth path length, voxels
    thresholds: Thresholds


def track_errors(pred, gt, spacing_mm=None, thresholds: Thresholds = Thresholds()) -> TrackErrors:
    e = frame_errors(pred, gt, spacing_mm)
    trans, rot = relative_pose_errors(pred, gt, thresholds.gap)
    return TrackErrors(e["pos"], e["pos_mm"], e["rot"], trans, rot, path_length(gt), thresholds)


def _tracked_share(pos: np.ndarray, bound: float, e: TrackErrors) -> float:
    """Percent of frames 1..N-1 with a position error below ``bound`` and a rotation error below the angle."""
    later = slice(1, None)
    tracked = (pos[later] < bound) & (e.rot[later] < e.thresholds.angle)
    return 100.0 * float(tracked.mean()) if tracked.size else math.nan


def ctf(e: TrackErrors) -> float:
    return _tracked_share(e.pos, e.thresholds.position, e)


def ctf_mm(e: TrackErrors) -> float:
    return _tracked_share(e.pos_mm, e.thresholds.position_mm, e)


def ate(e: TrackErrors) -> float:
    return _rmse(e.pos)


def ate_mm(e: TrackErrors) -> float:
    return _rmse(e.pos_mm)


def rpe_trans(e: TrackErrors) -> float:
    return _rmse(e.rpe_trans)


def rpe_rot(e: TrackErrors) -> float:
    return _rmse(e.rpe_rot)


def drift(e: TrackErrors) -> float:
    return 100.0 * float(e.pos[-1]) / e.length if e.length > 0 else math.nan


def trajectory_metrics(pred, gt, spacing_mm=None, thresholds: Thresholds = Thresholds()) -> dict[str, float]:
    """Every registered per-trajectory metric (registry.metric_specs, the module doc's) for one trajectory
    (``pred``/``gt`` ``(N, 6)``, the same first pose), in registration order."""
    e = track_errors(pred, gt, spacing_mm, thresholds)
    return {spec.name: float(registry.resolve(spec, globals())(e)) for spec in registry.metric_specs(per="trajectory")}
