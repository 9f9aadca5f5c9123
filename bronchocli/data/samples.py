"""Trajectories -> training samples: relative-pose labels, windows of image pairs, whole trajectories.

* :func:`relative_labels` - the ``N-1`` relative poses of a trajectory in the
  ``world`` (paper) or ``camera`` (SE(3)) parameterisation, angles wrapped
  (bronchocli.geometry.relative_trajectory).
* :class:`SequenceDataset` - training items of ``n_pairs`` consecutive image
  pairs (``n_pairs + 1`` frames); ``n_pairs=1`` gives independent pairs for
  the baseline and OffsetNet. Window placement: bronchocli.data.windows.
* :class:`TrajectoryDataset` - one item per whole trajectory, for evaluation.

Frames come from a :class:`~bronchocli.data.cache.FrameCache` as uint8
``[T, 3, H, W]`` tensors (channel-first); the model side converts to float and
normalises. Both datasets are picklable: they hold compact NumPy arrays and
the cache's path, and each DataLoader worker memory-maps the cache itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import Dataset as TorchDataset

from .. import geometry
from ..errors import ConfigError, DataError
from .cache import FrameCache
from .reader import Trajectory
from .windows import window_starts


def relative_labels(traj: Trajectory, frame: str = "world") -> np.ndarray:
    """Relative poses between consecutive frames, ``(N-1, 6)`` float64, in pose frame ``frame``."""
    if frame not in geometry.POSE_FRAMES:
        raise ConfigError(f"pose frame {frame!r}: must be one of {', '.join(geometry.POSE_FRAMES)}")
    return geometry.relative_trajectory(traj.poses, frame)


@dataclass(frozen=True)
class Photometric:
    """Photometric augmentation (the poses stay valid because the geometry is untouched).

    One brightness shift, contrast factor and gamma per item (shared by all its
    frames, like a change of the bronchoscope's gain), Gaussian noise drawn
    per pixel. Works in [0, 1] floats and returns uint8 again.
    """

    brightness: float = 0.1  # additive shift ~ U(-b, b)
    contrast: float = 0.2  # factor about the item's mean ~ U(1-c, 1+c)
    gamma: float = 0.2  # exponent exp(U(-g, g))
    noise: float = 0.02  # std of additive Gaussian noise

    def __call__(self, frames: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        x = frames.astype(np.float32) / 255.0
        x = np.power(x, np.float32(np.exp(rng.uniform(-self.gamma, self.gamma))))
        mean = x.mean()
        x = (x - mean) * np.float32(rng.uniform(1 - self.contrast, 1 + self.contrast)) + mean
        x = x + np.float32(rng.uniform(-self.brightness, self.brightness))
        if self.noise > 0:
            x = x + rng.normal(0.0, self.noise, x.shape).astype(np.float32)
        return (np.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


class _Frames(TorchDataset):
    """Shared bits: the frame cache, labels of every trajectory, per-item augmentation."""

    def __init__(self, trajectories: Sequence[Trajectory], cache: FrameCache, frame: str,
                 augment: bool, seed: int):
        if not trajectories:
            raise DataError("no trajectories to sample from (is this split empty?)")
        self.cache = cache
        self.frame = frame
        self.keys = [t.key for t in trajectories]
        self.frame_index = [np.asarray(t.frame_index, dtype=np.int64) for t in trajectories]
        self.labels = [relative_labels(t, frame).astype(np.float32) for t in trajectories]
        self.augmentation = Photometric() if augment else None
        self.seed = int(seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Vary the augmentation per epoch (call before the epoch's DataLoader iterator is created)."""
        self.epoch = int(epoch)

    def _frames(self, index: int, fidx: np.ndarray) -> torch.Tensor:
        frames = self.cache.take(fidx)
        if self.augmentation is not None:
            rng = np.random.default_rng([self.seed, self.epoch, index])
            frames = self.augmentation(frames, rng)
        return torch.from_numpy(frames)


class SequenceDataset(_Frames):
    """Windows of ``n_pairs`` consecutive image pairs; consecutive windows share ``overlap`` pairs.

    Item: ``frames`` uint8 ``[n_pairs+1, 3, H, W]``, ``labels`` float32
    ``[n_pairs, 6]`` (label ``k`` is the motion from frame ``k`` to ``k+1``),
    ``key`` (trajectory) and ``start`` (index of its first pair in the
    trajectory). Trajectories shorter than a window are skipped
    (``self.skipped`` counts them).
    """

    def __init__(self, trajectories: Sequence[Trajectory], cache: FrameCache, n_pairs: int, overlap: int = 0,
                 frame: str = "world", augment: bool = False, seed: int = 0):
        super().__init__(trajectories, cache, frame, augment, seed)
        self.n_pairs, self.overlap = int(n_pairs), int(overlap)
        rows = [(ti, s) for ti, t in enumerate(trajectories)
                for s in window_starts(t.n_pairs, self.n_pairs, self.overlap)]
        self.skipped = sum(1 for t in trajectories if t.n_pairs < self.n_pairs)
        if not rows:
            longest = max(t.n_frames for t in trajectories)
            raise DataError(f"no trajectory has {self.n_pairs + 1} frames for a window of {self.n_pairs} pairs "
                            f"(longest: {longest} frames); lower data.window")
        self.windows = np.asarray(rows, dtype=np.int64)  # (n_windows, 2): trajectory, first pair

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, index: int) -> dict:
        ti, s = (int(v) for v in self.windows[index])
        n = self.n_pairs
        return {
            "frames": self._frames(index, self.frame_index[ti][s: s + n + 1]),
            "labels": torch.from_numpy(self.labels[ti][s: s + n].copy()),
            "key": self.keys[ti],
            "start": s,
        }


class TrajectoryDataset(_Frames):
    """One item per whole trajectory, for evaluation (recurrent state carried through the video).

    Item: ``frames`` uint8 ``[N, 3, H, W]``, ``labels`` float32 ``[N-1, 6]``,
    ``start`` float64 ``(6,)`` (first absolute pose), ``poses`` float64
    ``[N, 6]`` (absolute ground truth), ``key``. Lengths differ between
    trajectories: use ``batch_size=1`` (or a collate that pads).
    """

    def __init__(self, trajectories: Sequence[Trajectory], cache: FrameCache, frame: str = "world"):
        super().__init__(trajectories, cache, frame, augment=False, seed=0)
        self.poses = [np.asarray(t.poses, dtype=np.float64) for t in trajectories]

    def __len__(self) -> int:
        return len(self.keys)

    def __getitem__(self, index: int) -> dict:
        return {
            "frames": self._frames(index, self.frame_index[index]),
            "labels": torch.from_numpy(self.labels[index].copy()),
            "start": torch.from_numpy(self.poses[index][0].copy()),
            "poses": torch.from_numpy(self.poses[index].copy()),
            "key": self.keys[index],
        }
