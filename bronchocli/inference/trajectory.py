"""Visual odometry with a trained model: relative poses of a video, chained into a trajectory, scored when
ground truth exists.

``track(model, frames, ...)`` predicts the ``N-1`` relative poses of ``N``
frames (the model's pose frame, voxels and degrees), chains them from a first
pose (given, else the ground truth's first pose, else the identity pose
0,0,0,0,0,0) with the geometry core, and, with ground truth, scores them with
evaluation's own functions (``training.evaluate``): the per-pair mean and the
accumulated (endpoint) error of each metric, and the trajectory metrics
(``traj.*``: CTF, ATE, RPE, drift, with the run's ``eval:`` thresholds), for
the model and for both image-blind references (zero motion, and the run's training-mean relative
pose). Errors are always chained from the ground truth's first pose, as the
run's evaluation does, so they equal the run's logged per-trajectory errors
for one of its test trajectories (up to the fp16 rounding of the weights).

Outputs (``write``): ``trajectory.csv`` (one row per frame: ``frame``,
``source`` (file name or frame number), ``pos_x pos_y pos_z Rx Ry Rz`` as in a
dataset CSV, and the relative pose from the previous frame ``d_x .. d_rz``,
empty on frame 0), ``trajectory.png`` (3-D plot, voxel axes, with the ground
truth when known) and, with ground truth, ``errors.csv`` (evaluation's
per-trajectory table: ``<source>.<pair|acc>.<metric>``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from .. import geometry
from ..data.reader import DISK_POSE_COLUMNS
from ..errors import DataError
from ..io import atomic_path, save_figure
from ..plots import trajectory_figure
from ..training import evaluate
from .mlflow_model import PoseModel, warn_resize
from .reader import FrameInput, GroundTruth

REL_COLUMNS = ("d_x", "d_y", "d_z", "d_rx", "d_ry", "d_rz")
PROGRESS_MIN_FRAMES = 64  # shorter inputs finish before a bar would tell anything


@dataclass(frozen=True)
class TrackResult:
    relative: np.ndarray  # (N-1, 6) predicted relative poses, the model's pose frame
    poses: np.ndarray  # (N, 6) chained absolute poses from ``first_pose``
    first_pose: np.ndarray  # (6,)
    pose_frame: str
    labels: tuple[str, ...]
    truth: GroundTruth | None = None
    errors: pd.DataFrame | None = None  # one row: evaluate.trajectory_table of the model and both references


def parse_pose(text: str) -> np.ndarray:
    """``"x,y,z,a,b,g"`` (voxels, degrees) -> a pose 6-vector; DataError naming the value otherwise."""
    try:
        values = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        values = []
    if len(values) != 6 or not np.isfinite(values).all():
        raise DataError(f"--first-pose {text!r}: expected six numbers x,y,z,rx,ry,rz (voxels, degrees)")
    return np.asarray(values, dtype=np.float64)


@contextmanager
def _progress(show: bool, total: int | None, label: str) -> Iterator:
    if not show or (total is not None and total < PROGRESS_MIN_FRAMES):
        yield lambda n: None
        return
    with Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TextColumn("frames"), TimeElapsedColumn(),
                  TimeRemainingColumn(), transient=True) as bar:
        task = bar.add_task(label, total=total)
        yield lambda n: bar.advance(task, n)


def _check_length(inp: FrameInput, n: int, truth: GroundTruth) -> None:
    if len(truth.poses) != n:
        raise DataError(f"{truth.source or 'ground truth'}: {len(truth.poses)} poses for the {n} frames of "
                        f"{inp.name}; give one pose per frame")


def score(model: PoseModel, relative: np.ndarray, truth: GroundTruth, key: str = "") -> pd.DataFrame:
    """Evaluation's per-trajectory table (model and both references) for one predicted trajectory."""
    frame = model.pose_frame
    gt_abs = geometry.canonical_pose(np.asarray(truth.poses, dtype=np.float64))  # one triple per rotation
    key = key or truth.key
    patient, lobe, traj = (key.split("/", 2) + ["", ""])[:3] if key else ("", "", "")
    pred = evaluate.TrajectoryPrediction(
        key=key, patient=patient, lobe=lobe, traj_id=traj,
        gt_rel=geometry.relative_trajectory(gt_abs, frame), pred_rel=np.asarray(relative, dtype=np.float64),
        gt_abs=gt_abs, pred_abs=geometry.accumulate(gt_abs[0], relative, frame),
        spacing_mm=np.asarray(truth.spacing_mm, dtype=np.float64), frame=frame)
    return evaluate.trajectory_table([pred], evaluate.reference_predictions([pred], model.train_mean, frame),
                                     model.thresholds)


def track(model: PoseModel, inp: FrameInput, first_pose: np.ndarray | None = None,
          truth: GroundTruth | None = None, progress: bool = True) -> TrackResult:
    """Predict, chain and (with ground truth: ``truth`` or the input's own) score one input (module doc)."""
    truth = truth if truth is not None else inp.ground_truth
    if inp.shape != (model.image_size, model.image_size):
        warn_resize(inp.shape, model.image_size, what=f"{inp.name}: frames")
    if truth is not None and inp.n_frames is not None:
        _check_length(inp, inp.n_frames, truth)
    with _progress(progress, inp.n_frames, f"track {Path(inp.name).name}") as advance:
        relative = model.relative_poses(inp.frames(), on_frames=advance)
    n = len(relative) + 1
    if truth is not None:
        _check_length(inp, n, truth)
    if first_pose is None:
        first_pose = truth.poses[0] if truth is not None else np.zeros(6)
    poses = geometry.accumulate(np.asarray(first_pose, dtype=np.float64), relative, model.pose_frame)
    labels = inp.labels if len(inp.labels) == n else tuple(str(i) for i in range(n))
    errors = score(model, relative, truth) if truth is not None else None
    return TrackResult(relative, poses, np.asarray(first_pose, dtype=np.float64), model.pose_frame, labels, truth,
                       errors)


def trajectory_table(result: TrackResult) -> pd.DataFrame:
    """One row per frame: absolute pose (dataset CSV names) and the relative pose from the previous frame."""
    n = len(result.poses)
    table = pd.DataFrame({"frame": np.arange(n), "source": list(result.labels)})
    for j, c in enumerate(DISK_POSE_COLUMNS):
        table[c] = result.poses[:, j]
    rel = np.vstack([np.full((1, 6), np.nan), result.relative])
    for j, c in enumerate(REL_COLUMNS):
        table[c] = rel[:, j]
    return table


def write(result: TrackResult, out: Path, title: str = "", model_label: str = "model") -> list[Path]:
    """``trajectory.csv``, ``trajectory.png`` and (with ground truth) ``errors.csv`` under ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    with atomic_path(out / "trajectory.csv") as tmp:
        trajectory_table(result).to_csv(tmp, index=False)
    written.append(out / "trajectory.csv")
    gt = result.truth.poses if result.truth is not None else None
    fig = trajectory_figure([gt], {model_label: [result.poses]}, titles=[title] if title else None)
    written += save_figure(fig, out / "trajectory")
    if result.errors is not None:
        with atomic_path(out / "errors.csv") as tmp:
            result.errors.to_csv(tmp, index=False)
        written.append(out / "errors.csv")
    return written
