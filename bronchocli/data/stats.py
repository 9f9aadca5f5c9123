"""Summaries of a dataset and of a split, as tables (what ``bronchopose data stats`` prints)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from .gimbal import world_label_jumps
from .reader import POSE_COLUMNS, Dataset
from .splits import Split
from .windows import window_starts


def per_lobe(dataset: Dataset) -> pd.DataFrame:
    """Per patient and lobe: trajectories, frames, pairs and trajectory length (frames) min/mean/max."""
    rows = []
    for patient in dataset.patients:
        for lobe in dataset.lobes:
            lengths = np.array([t.n_frames for t in dataset.of(patient, lobe)])
            if len(lengths):
                rows.append((patient, lobe, len(lengths), int(lengths.sum()), int(lengths.sum() - len(lengths)),
                             int(lengths.min()), float(lengths.mean()), int(lengths.max())))
    return pd.DataFrame(rows, columns=["patient", "lobe", "trajectories", "frames", "pairs",
                                       "len_min", "len_mean", "len_max"])


def pose_ranges(dataset: Dataset) -> pd.DataFrame:
    """Minimum and maximum of each pose component (voxels, degrees) and of the per-pair world motion."""
    poses = dataset.frames[list(POSE_COLUMNS)].to_numpy()
    steps = np.concatenate([np.diff(t.poses[:, :3], axis=0) for t in dataset.trajectories])
    step = np.linalg.norm(steps, axis=1)
    rows = [(c, float(poses[:, i].min()), float(poses[:, i].max())) for i, c in enumerate(POSE_COLUMNS)]
    rows.append(("step (voxels/pair)", float(step.min()), float(step.max())))
    return pd.DataFrame(rows, columns=["component", "min", "max"])


def overview(dataset: Dataset) -> dict[str, str]:
    """One-line facts: root, format, counts, image size, fingerprint."""
    h, w = dataset.frame_shape
    return {
        "root": str(dataset.root),
        "format": dataset.format,
        "patients": ", ".join(dataset.patients),
        "lobes": ", ".join(dataset.lobes),
        "trajectories": str(len(dataset.trajectories)),
        "frames": str(dataset.n_frames),
        "image size": f"{w}x{h}" if dataset.has_frames else "none (poses only)",
        "fingerprint": dataset.fingerprint,
    }


def split_counts(split: Split, window: int, overlap: int) -> pd.DataFrame:
    """Per split: patients, trajectories, frames, pairs, and training windows of ``window`` pairs."""
    rows = []
    for part, trajs in split.parts().items():
        windows = sum(len(window_starts(t.n_pairs, window, overlap)) for t in trajs)
        rows.append((part, len({t.patient for t in trajs}), len(trajs), sum(t.n_frames for t in trajs),
                     sum(t.n_pairs for t in trajs), windows))
    return pd.DataFrame(rows, columns=["split", "patients", "trajectories", "frames", "pairs",
                                       f"windows({window})"])


def split_per_patient(split: Split, dataset: Dataset) -> pd.DataFrame:
    """Trajectories per patient and lobe (dataset order) in each split (columns train, val, test)."""
    where = {t.key: part for part, trajs in split.parts().items() for t in trajs}
    rows = []
    for patient in dataset.patients:
        for lobe in dataset.lobes:
            parts = [where.get(t.key) for t in dataset.of(patient, lobe)]
            if parts:
                rows.append((patient, lobe, *(parts.count(p) for p in ("train", "val", "test"))))
    return pd.DataFrame(rows, columns=["patient", "lobe", "train", "val", "test"])


def gimbal_table(dataset: Dataset) -> pd.DataFrame:
    """Trajectories whose world-frame labels are not their motion (near gimbal lock, gimbal.py): the frames,
    the largest Euler-difference norm and true rotation there, and the trajectory's largest |beta|."""
    rows = [(j.key, ", ".join(map(str, j.frames)) if len(j.frames) <= 12 else
             f"{', '.join(map(str, j.frames[:12]))} and {len(j.frames) - 12} more", len(j.frames),
             j.euler_max, j.rotation_max, j.beta_max) for j in world_label_jumps(dataset)]
    return pd.DataFrame(rows, columns=["trajectory", "frames", "pairs", "euler_diff_max_deg", "rotation_max_deg",
                                       "abs_beta_max_deg"])
