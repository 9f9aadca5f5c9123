"""Evaluation on whole test trajectories: metrics, image-blind references, per-trajectory errors.

Each test video is processed from its first frame to its last in chunks of
``chunk`` pairs (chunks overlap by one frame); a recurrent model carries its
state through the whole video, as a tracker would. Predicted relative poses are
chained from the true first pose with the geometry core (sum in the ``world``
pose frame, composition in ``camera``).

Metric names are stable (MLflow keys and report columns), one per metric
registered in registry.py: ``pair.<m>.{mean,std}`` over all pairs of all test
trajectories, ``acc.<m>.{mean,std}`` over trajectories (endpoint after
chaining the whole trajectory) for each per-pose metric (pos_l2, pos_l2_mm,
rot_l2, de, ce, geodesic), and ``traj.<t>.{mean,std}`` over trajectories for
each per-trajectory one, the camera-tracking metrics of the literature
(odometry.py: ctf, ctf_mm, ate, ate_mm, rpe_trans, rpe_rot, drift; thresholds
from the config's ``eval:`` section).

Two image-blind references are scored on the same trajectories with the same
metrics, under the prefixes ``zero_motion.`` (every relative pose is zero) and
``train_mean.`` (every relative pose is the mean of the training labels, in the
run's pose frame): a model must beat the better of them to have learnt anything
from the images. ``pred.std.*`` says how much the predictions vary across test
pairs (about 0 for a model that ignores its input).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
import torch

from .. import geometry, metrics, odometry, registry, runkeys
from ..data.batches import FrameSource, relative_labels
from ..data.reader import Trajectory

POSE_COLS = ("x", "y", "z", "rx", "ry", "rz")
REFERENCES = runkeys.REFERENCES  # the image-blind references, in the order their keys are logged


@dataclass(frozen=True)
class TrajectoryPrediction:
    key: str
    patient: str
    lobe: str
    traj_id: str
    gt_rel: np.ndarray  # (N-1, 6)
    pred_rel: np.ndarray  # (N-1, 6)
    gt_abs: np.ndarray  # (N, 6)
    pred_abs: np.ndarray  # (N, 6)
    spacing_mm: np.ndarray  # (3,)
    frame: str = "world"  # the pose frame of gt_rel/pred_rel: in ``camera`` they are rotations


def thresholds(section) -> odometry.Thresholds:
    """The config's ``eval:`` section (config.EvalCfg) as odometry thresholds."""
    return odometry.Thresholds(position=section.ctf_position, position_mm=section.ctf_position_mm,
                               angle=section.ctf_angle, gap=section.rpe_gap)


@torch.no_grad()
def predict_relative(net, frames: torch.Tensor, chunk: int, autocast=None) -> np.ndarray:
    """Relative poses ``(N-1, 6)`` for one video ``frames`` uint8 ``[N, 3, H, W]`` on the model's device."""
    n_pairs = frames.shape[0] - 1
    outputs, state = [], None
    for start in range(0, n_pairs, chunk):
        clip = frames[start: start + chunk + 1].unsqueeze(0)
        if autocast is None:
            out, state = net(clip, state)
        else:
            with autocast():
                out, state = net(clip, state)
        outputs.append(out[0].double().cpu())
    return torch.cat(outputs).numpy()


def predict_trajectories(net, trajectories: Sequence[Trajectory], source: FrameSource, frame: str, chunk: int,
                         spacing: dict[str, np.ndarray], autocast=None) -> list[TrajectoryPrediction]:
    """Run the model over every trajectory (eval mode) and chain its predictions."""
    net.eval()
    preds = []
    for t in trajectories:
        pred_rel = predict_relative(net, source(np.asarray(t.frame_index)), chunk, autocast)
        gt_abs = np.asarray(t.poses, dtype=np.float64)
        preds.append(TrajectoryPrediction(
            key=t.key, patient=t.patient, lobe=t.lobe, traj_id=str(t.traj_id),
            gt_rel=relative_labels(t, frame), pred_rel=pred_rel, gt_abs=gt_abs,
            pred_abs=geometry.accumulate(gt_abs[0], pred_rel, frame),
            spacing_mm=np.asarray(spacing[t.patient], dtype=np.float64), frame=frame,
        ))
    return preds


def _stats(scope: str, stats: dict[str, metrics.Stat], ref: str | None) -> dict[str, float]:
    out = {}
    for name, s in stats.items():
        out[runkeys.metric(name, scope, "mean", ref)] = s.mean
        out[runkeys.metric(name, scope, "std", ref)] = s.std
    return out


def _deltas_are_rotations(preds: Sequence[TrajectoryPrediction]) -> bool:
    """``camera``-frame relative poses are rotations (compared as such); ``world`` ones are angle differences."""
    return any(p.frame == "camera" for p in preds)


def odometry_metrics(p: TrajectoryPrediction, thresholds: odometry.Thresholds) -> dict[str, float]:
    return odometry.trajectory_metrics(p.pred_abs, p.gt_abs, p.spacing_mm, thresholds)


def score(preds: list[TrajectoryPrediction], thresholds: odometry.Thresholds = odometry.Thresholds(),
          ref: str | None = None) -> dict[str, float]:
    """Every test metric of a set of predicted trajectories; ``ref``: a reference's (its keys carry its name, and
    the test set's size is the model's, not repeated)."""
    if not preds:
        raise ValueError("no test trajectories to score")
    pred = np.concatenate([p.pred_rel for p in preds])
    gt = np.concatenate([p.gt_rel for p in preds])
    spacing = np.concatenate([np.repeat(p.spacing_mm[None], len(p.gt_rel), 0) for p in preds])
    out = _stats("pair", metrics.pair_metrics(pred, gt, spacing, rotations=_deltas_are_rotations(preds)), ref)
    ends_pred = np.stack([p.pred_abs[-1] for p in preds])
    ends_gt = np.stack([p.gt_abs[-1] for p in preds])
    out |= _stats("acc", metrics.pair_metrics(ends_pred, ends_gt, np.stack([p.spacing_mm for p in preds]),
                                              rotations=True), ref)
    per_traj = [odometry_metrics(p, thresholds) for p in preds]
    traj = {k: np.array([m[k] for m in per_traj]) for k in registry.metric_names(per="trajectory")}
    out |= _stats("traj", {k: metrics.Stat.of(v[np.isfinite(v)]) for k, v in traj.items()}, ref)
    if ref is None:
        out[runkeys.count("pair")] = float(len(gt))
        out[runkeys.count("traj")] = float(len(preds))
    return out


def constant_predictions(preds: list[TrajectoryPrediction], constant: np.ndarray, frame: str
                         ) -> list[TrajectoryPrediction]:
    """The same trajectories predicted by an image-blind model that always outputs ``constant``."""
    out = []
    for p in preds:
        rel = np.broadcast_to(np.asarray(constant, dtype=np.float64), p.gt_rel.shape).copy()
        out.append(replace(p, pred_rel=rel, pred_abs=geometry.accumulate(p.gt_abs[0], rel, frame)))
    return out


def reference_predictions(preds: list[TrajectoryPrediction], train_mean: np.ndarray, frame: str
                          ) -> dict[str, list[TrajectoryPrediction]]:
    zero_motion, mean = REFERENCES
    return {zero_motion: constant_predictions(preds, np.zeros(6), frame),
            mean: constant_predictions(preds, train_mean, frame)}


def variability(preds: list[TrajectoryPrediction]) -> dict[str, float]:
    """How much predictions vary across test pairs, against the ground truth's own variation.

    ``pred.std.pos`` / ``pred.std.rot``: the std over test pairs of the predicted
    position (voxels) / angle (degrees) components, averaged over the three axes;
    ``pred.std_ratio.*``: the same divided by the ground truth's (0: the model
    ignores its input; near 1: it varies as much as the truth).
    """
    pred = np.concatenate([p.pred_rel for p in preds])
    gt = np.concatenate([p.gt_rel for p in preds])
    out = {}
    for name, cols in (("pos", slice(0, 3)), ("rot", slice(3, 6))):
        ps, gs = float(pred[:, cols].std(0).mean()), float(gt[:, cols].std(0).mean())
        out[runkeys.spread(name)] = ps
        out[runkeys.spread(name, relative=True)] = ps / gs if gs > 0 else float("nan")
    return out


def trajectory_table(preds: list[TrajectoryPrediction], references: dict[str, list[TrajectoryPrediction]],
                     thresholds: odometry.Thresholds = odometry.Thresholds()) -> pd.DataFrame:
    """One row per test trajectory: its mean per-pair error and its endpoint (accumulated) error per metric,
    and its camera-tracking metrics, for the model and each reference (columns ``<source>.<pair|acc>.<metric>``
    and ``<source>.traj.<t>``). What ``report`` pairs rows on to compare two models on the same trajectories."""
    rows = []
    sources = {runkeys.MODEL: preds, **references}
    for i, p in enumerate(preds):
        row: dict[str, object] = {"patient": p.patient, "lobe": p.lobe, "trajectory": p.traj_id,
                                  "n_pairs": len(p.gt_rel)}
        for name, ps in sources.items():
            q = ps[i]
            pair = metrics.per_pose_errors(q.pred_rel, q.gt_rel, p.spacing_mm, rotations=q.frame == "camera")
            acc = metrics.per_pose_errors(q.pred_abs[-1:], q.gt_abs[-1:], p.spacing_mm, rotations=True)
            for m in pair:  # every per-pose metric (registry.py; the mm ones: the spacing is known here)
                row[runkeys.column(m, "pair", name)] = float(np.mean(pair[m]))
                row[runkeys.column(m, "acc", name)] = float(acc[m][0])
            for m, v in odometry_metrics(q, thresholds).items():
                row[runkeys.column(m, "traj", name)] = v
        rows.append(row)
    return pd.DataFrame(rows)


def evaluate(preds: list[TrajectoryPrediction], train_mean: np.ndarray, frame: str,
             thresholds: odometry.Thresholds = odometry.Thresholds()) -> tuple[dict[str, float], pd.DataFrame]:
    """Metrics of the model and of both references, prediction variability, and the per-trajectory table."""
    refs = reference_predictions(preds, train_mean, frame)
    out = score(preds, thresholds)
    for name, ref in refs.items():
        out |= score(ref, thresholds, ref=name)
    out |= variability(preds)  # the thresholds are config constants: params (artifacts.log_outcome), not metrics
    return out, trajectory_table(preds, refs, thresholds)


def predictions_table(preds: list[TrajectoryPrediction], train_mean: list[TrajectoryPrediction] | None = None
                      ) -> pd.DataFrame:
    """One row per frame: ground truth and prediction, relative (NaN for frame 0) and accumulated; with
    ``train_mean`` (``reference_predictions``' training-mean reference of the same trajectories), its accumulated
    pose too (``train_mean_abs_*``: the report's error-vs-frame figures draw it as a reference line)."""
    frames = []
    for i, p in enumerate(preds):
        n = len(p.gt_abs)
        nan = np.full((1, 6), np.nan)
        cols = {"patient": p.patient, "lobe": p.lobe, "trajectory": p.traj_id, "frame": np.arange(n)}
        blocks = {"gt_rel": np.vstack([nan, p.gt_rel]), "pred_rel": np.vstack([nan, p.pred_rel]),
                  "gt_abs": p.gt_abs, "pred_abs": p.pred_abs}
        if train_mean is not None:
            blocks[f"{REFERENCES[1]}_abs"] = train_mean[i].pred_abs
        for prefix, block in blocks.items():
            for j, c in enumerate(POSE_COLS):
                cols[f"{prefix}_{c}"] = block[:, j]
        frames.append(pd.DataFrame(cols))
    return pd.concat(frames, ignore_index=True)
