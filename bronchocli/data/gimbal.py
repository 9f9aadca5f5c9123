"""World-frame labels near gimbal lock: where Euler differences are far larger than the rotation between frames.

The paper's ``world`` labels are plain differences of XYZ Euler angles. Near
gimbal lock (|beta| -> 90°) alpha and gamma swing through large angles while
the camera hardly turns, so those differences stop describing the motion: a
real endoscope trajectory with beta down to -88.9° has 89 steps whose Euler
differences exceed 20° (up to 135.6°) while the true rotation between frames
stays <= 63.5°. Training on such labels is training on noise. ``camera``
labels (the relative rotation R_{t-1}^T R_t) have no such problem: the
relative rotation between two frames is small whenever the motion is small
(docs/conventions.md).

``world_label_jumps`` finds, per trajectory, the pairs whose Euler difference
(the norm of the three wrapped angle differences) exceeds the geodesic angle
between the two orientations by more than ``MARGIN_DEG`` and by more than a
factor ``RATIO``; ``world_label_warning`` turns them into one line naming the
trajectories and frames. It is given at import (``import_csv``), by
``bronchopose data stats`` and by training cells with ``pose_frame: world``.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .. import geometry
from .reader import Dataset, Trajectory

MARGIN_DEG = 10.0  # the Euler difference exceeds the true rotation by more than this ...
RATIO = 2.0  # ... and by more than this factor (away from lock they differ by < 2x: 1 / cos(60°))
SHOWN = 3  # trajectories named in the warning line


@dataclass(frozen=True)
class Jumps:
    """The pairs of one trajectory whose world-frame label is not its motion."""

    key: str  # patient/lobe/trajectory
    frames: tuple[int, ...]  # the later frame (the dataset's frame number) of each such pair
    euler_max: float  # the largest Euler-difference norm there, degrees
    rotation_max: float  # the largest true rotation between frames there, degrees
    beta_max: float  # the largest |beta| of the trajectory, degrees


def pair_angles(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair of consecutive poses ``(N, 6)``: the norm of the wrapped Euler differences (the ``world``
    label's rotation part) and the geodesic angle between the two orientations, both in degrees."""
    euler = np.linalg.norm(geometry.wrap_deg(np.diff(poses[:, 3:], axis=0)), axis=1)
    R = geometry.euler_to_matrix(poses[:, 3:])
    rel = np.swapaxes(R[:-1], -1, -2) @ R[1:]
    vee = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    true = np.degrees(np.arctan2(np.linalg.norm(vee, axis=1), np.trace(rel, axis1=1, axis2=2) - 1.0))
    return euler, true


def trajectory_jumps(traj: Trajectory, frame_numbers: np.ndarray) -> Jumps | None:
    """The trajectory's pairs whose Euler difference is far larger than its rotation, or None."""
    if traj.n_frames < 2:
        return None
    euler, true = pair_angles(traj.poses)
    bad = (euler - true > MARGIN_DEG) & (euler > RATIO * true)
    if not bad.any():
        return None
    later = frame_numbers[1:][bad]
    return Jumps(traj.key, tuple(int(f) for f in later), float(euler[bad].max()), float(true[bad].max()),
                 float(np.abs(traj.poses[:, 4]).max()))


def world_label_jumps(dataset: Dataset) -> list[Jumps]:
    """Every trajectory of ``dataset`` with world-frame labels near gimbal lock (dataset order)."""
    numbers = dataset.frames["frame"].to_numpy() if "frame" in dataset.frames else None
    out = []
    for traj in dataset.trajectories:
        frames = numbers[traj.frame_index] if numbers is not None else np.arange(traj.n_frames)
        found = trajectory_jumps(traj, np.asarray(frames))
        if found is not None:
            out.append(found)
    return out


def frame_ranges(frames: Sequence[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``'3-5, 9'``."""
    parts: list[str] = []
    start = prev = None
    for f in sorted(frames):
        if prev is not None and f == prev + 1:
            prev = f
            continue
        if start is not None:
            parts.append(str(start) if start == prev else f"{start}-{prev}")
        start = prev = f
    if start is not None:
        parts.append(str(start) if start == prev else f"{start}-{prev}")
    return ", ".join(parts)


def describe(jumps: Sequence[Jumps], total: int) -> str:
    """One line: how many trajectories, the first few with their frames, what it means and what to do."""
    named = "; ".join(f"{j.key} frames {frame_ranges(j.frames)} (Euler differences up to {j.euler_max:.1f}° where "
                      f"the camera turned at most {j.rotation_max:.1f}°, |beta| up to {j.beta_max:.1f}°)"
                      for j in jumps[:SHOWN])
    more = f"; and {len(jumps) - SHOWN} more trajector{'y' if len(jumps) - SHOWN == 1 else 'ies'}" \
        if len(jumps) > SHOWN else ""
    return (f"world-frame labels near gimbal lock in {len(jumps)} of {total} trajector"
            f"{'y' if total == 1 else 'ies'}: {named}{more}. There the Euler-angle differences (pose_frame world, "
            f"the paper's labels) are not the camera's motion; camera-frame labels are unaffected "
            f"(grid.pose_frame: [camera]; docs/conventions.md)")


_checked: "weakref.WeakKeyDictionary[Dataset, str]" = weakref.WeakKeyDictionary()


def world_label_warning(dataset: Dataset) -> str:
    """The warning line for ``dataset`` ("" when no trajectory is affected); computed once per dataset object."""
    if dataset not in _checked:
        jumps = world_label_jumps(dataset)
        _checked[dataset] = f"dataset {dataset.root}: {describe(jumps, len(dataset.trajectories))}" if jumps else ""
    return _checked[dataset]
