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

The names avoid ``tracking``: in this project that word means MLflow run
tracking (tracking.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import geometry

METRICS = ("ctf", "ctf_mm", "ate", "ate_mm", "rpe_trans", "rpe_rot", "drift")
HIGHER_IS_BETTER = frozenset({"ctf", "ctf_mm"})
UNITS = {"ctf": "%", "ctf_mm": "%", "ate": "voxels", "ate_mm": "mm", "rpe_trans": "voxels", "rpe_rot": "degrees",
         "drift": "% of path"}


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


def trajectory_metrics(pred, gt, spacing_mm=None, thresholds: Thresholds = Thresholds()) -> dict[str, float]:
    """Every metric of the module doc for one trajectory (``pred``/``gt`` ``(N, 6)``, the same first pose)."""
    e = frame_errors(pred, gt, spacing_mm)
    later = slice(1, None)
    ok_rot = e["rot"][later] < thresholds.angle
    tracked = (e["pos"][later] < thresholds.position) & ok_rot
    tracked_mm = (e["pos_mm"][later] < thresholds.position_mm) & ok_rot
    trans, rot = relative_pose_errors(pred, gt, thresholds.gap)
    length = path_length(gt)
    return {
        "ctf": 100.0 * float(tracked.mean()) if tracked.size else math.nan,
        "ctf_mm": 100.0 * float(tracked_mm.mean()) if tracked_mm.size else math.nan,
        "ate": _rmse(e["pos"]),
        "ate_mm": _rmse(e["pos_mm"]),
        "rpe_trans": _rmse(trans),
        "rpe_rot": _rmse(rot),
        "drift": 100.0 * float(e["pos"][-1]) / length if length > 0 else math.nan,
    }
