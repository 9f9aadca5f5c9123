"""Evaluation on whole test trajectories: per-pair, accumulated and trajectory metrics, predictions table.

Each test video is processed from its first frame to its last in chunks of
``chunk`` pairs (chunks overlap by one frame); a recurrent model carries its
state through the whole video, as a tracker would. Predicted relative poses are
chained from the true first pose with the geometry core (sum in the ``world``
pose frame, composition in ``camera``).

Metric names are stable (MLflow keys and report columns):
``pair.<m>.{mean,std}`` over all pairs of all test trajectories,
``acc.<m>.{mean,std}`` over trajectories (endpoint after chaining the whole
trajectory), ``traj.{ate,ate_mm,rpe_trans,rpe_rot}.{mean,std}``, with
``<m>`` in pos_l2, pos_l2_mm, rot_l2, de, ce, geodesic.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np
import pandas as pd
import torch

from .. import geometry, metrics

POSE_COLS = ("x", "y", "z", "rx", "ry", "rz")


@dataclass
class TrajectoryPrediction:
    key: str
    patient: str
    lobe: str
    traj_id: Any
    gt_rel: np.ndarray  # (N-1, 6)
    pred_rel: np.ndarray  # (N-1, 6)
    gt_abs: np.ndarray  # (N, 6)
    pred_abs: np.ndarray  # (N, 6)
    spacing_mm: np.ndarray  # (3,)


@torch.no_grad()
def predict_relative(module, frames: torch.Tensor, chunk: int) -> np.ndarray:
    """Relative poses ``(N-1, 6)`` for one video ``frames`` uint8 ``[N, 3, H, W]``."""
    n_pairs = frames.shape[0] - 1
    outputs, state = [], None
    for start in range(0, n_pairs, chunk):
        clip = frames[start : start + chunk + 1].unsqueeze(0)
        out, state = module(clip, state)
        outputs.append(out[0].double().cpu())
    return torch.cat(outputs).numpy()


def predict_trajectories(module, items: Iterable[dict[str, Any]], frame: str, chunk: int) -> list[TrajectoryPrediction]:
    """Run the model over every trajectory item (from the data layer's TrajectoryDataset)."""
    module.eval()
    preds = []
    for item in items:
        pred_rel = predict_relative(module, item["frames"], chunk)
        start = np.asarray(item["start"], dtype=np.float64)
        gt_abs = np.asarray(item["poses"], dtype=np.float64)
        preds.append(TrajectoryPrediction(
            key=item["key"], patient=item["patient"], lobe=item["lobe"], traj_id=item["traj_id"],
            gt_rel=np.asarray(item["labels"], dtype=np.float64), pred_rel=pred_rel,
            gt_abs=gt_abs, pred_abs=geometry.accumulate(start, pred_rel, frame),
            spacing_mm=np.asarray(item["spacing_mm"], dtype=np.float64),
        ))
    return preds


def _stats(prefix: str, stats: dict[str, metrics.Stat]) -> dict[str, float]:
    out = {}
    for name, s in stats.items():
        out[f"{prefix}.{name}.mean"] = s.mean
        out[f"{prefix}.{name}.std"] = s.std
    return out


def score(preds: list[TrajectoryPrediction], frame: str) -> dict[str, float]:
    """Every test metric of a set of predicted trajectories."""
    if not preds:
        raise ValueError("no test trajectories to score")
    pred = np.concatenate([p.pred_rel for p in preds])
    gt = np.concatenate([p.gt_rel for p in preds])
    spacing = np.concatenate([np.repeat(p.spacing_mm[None], len(p.gt_rel), 0) for p in preds])
    out = _stats("pair", metrics.pair_metrics(pred, gt, spacing))
    ends_pred = np.stack([p.pred_abs[-1] for p in preds])
    ends_gt = np.stack([p.gt_abs[-1] for p in preds])
    out |= _stats("acc", metrics.pair_metrics(ends_pred, ends_gt, np.stack([p.spacing_mm for p in preds])))
    errs = [metrics.trajectory_errors(p.pred_abs, p.gt_abs) for p in preds]
    mean_spacing = np.array([float(np.mean(p.spacing_mm)) for p in preds])
    traj = {
        "ate": np.concatenate([e["ate"] for e in errs]),
        "rpe_trans": np.concatenate([e["rpe_trans"] for e in errs]),
        "rpe_rot": np.concatenate([e["rpe_rot"] for e in errs]),
    }
    traj["ate_mm"] = traj["ate"] * mean_spacing
    out |= _stats("traj", {k: metrics.Stat.of(v) for k, v in traj.items()})
    out["test.n_pairs"] = float(len(gt))
    out["test.n_trajectories"] = float(len(preds))
    return out


def zero_motion_score(preds: list[TrajectoryPrediction], frame: str) -> dict[str, float]:
    """The same metrics for a predictor that always says "no motion" (a floor any model must beat)."""
    zero = [
        TrajectoryPrediction(**{**p.__dict__, "pred_rel": np.zeros_like(p.gt_rel),
                                "pred_abs": geometry.accumulate(p.gt_abs[0], np.zeros_like(p.gt_rel), frame)})
        for p in preds
    ]
    return score(zero, frame)


def predictions_table(preds: list[TrajectoryPrediction]) -> pd.DataFrame:
    """One row per frame: ground truth and prediction, relative (NaN for frame 0) and accumulated."""
    frames = []
    for p in preds:
        n = len(p.gt_abs)
        nan = np.full((1, 6), np.nan)
        cols = {"patient": p.patient, "lobe": p.lobe, "trajectory": p.traj_id, "frame": np.arange(n)}
        blocks = {"gt_rel": np.vstack([nan, p.gt_rel]), "pred_rel": np.vstack([nan, p.pred_rel]),
                  "gt_abs": p.gt_abs, "pred_abs": p.pred_abs}
        for prefix, block in blocks.items():
            for j, c in enumerate(POSE_COLS):
                cols[f"{prefix}_{c}"] = block[:, j]
        frames.append(pd.DataFrame(cols))
    return pd.concat(frames, ignore_index=True)
