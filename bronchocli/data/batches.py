"""Samples as index arrays over the frame cache, their batch order, and the frames they point at.

A :class:`Samples` set is a few arrays: ``frames`` (global frame indices,
``[N, P+1]``) and ``labels`` (``[N, P, 6]``, the relative pose of each of the
``P`` consecutive image pairs in the chosen pose frame). Pairwise models use
``P = 1``, temporal models windows of ``P = L·K`` pairs. :class:`BatchOrder`
shuffles them per epoch, deterministically in (seed, epoch), so the ``i``-th
batch of a run is known from ``i`` alone and a resumed run continues exactly.
A :class:`FrameSource` turns a batch of frame indices into uint8 frames
``[B, P+1, 3, H, W]`` on the training device: gathered from a copy of the
cache in device memory when it fits, else read from the memory-mapped cache
(pinned host memory and an asynchronous copy on CUDA). :func:`photometric`
augments on the device.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .. import geometry
from ..errors import DataError
from .cache import FrameCache
from .reader import Trajectory
from .windows import window_starts


def relative_labels(traj: Trajectory, frame: str = "world") -> np.ndarray:
    """Relative poses between consecutive frames, ``(N-1, 6)`` float64, in pose frame ``frame``."""
    return geometry.relative_trajectory(traj.poses, frame)


@dataclass(frozen=True)
class Samples:
    """``N`` samples of ``P`` consecutive image pairs each (see the module doc)."""

    frames: np.ndarray  # int64 [N, P+1] global frame indices
    labels: np.ndarray  # float32 [N, P, 6]
    trajectory: np.ndarray  # int64 [N]: index into ``keys``
    start: np.ndarray  # int64 [N]: first pair of the sample within its trajectory
    keys: tuple[str, ...]
    skipped: int = 0  # trajectories too short for one sample

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def n_pairs(self) -> int:
        return self.labels.shape[1]

    def subset(self, index: Sequence[int] | np.ndarray) -> Samples:
        idx = np.asarray(index, dtype=np.int64)
        return Samples(self.frames[idx], self.labels[idx], self.trajectory[idx], self.start[idx], self.keys,
                       self.skipped)

    def evenly(self, max_pairs: int | None) -> Samples:
        """At most ``max_pairs`` pairs' worth of samples, evenly spread (the same every call)."""
        if max_pairs is None or len(self) * self.n_pairs <= max_pairs:
            return self
        keep = max(1, max_pairs // self.n_pairs)
        return self.subset(np.linspace(0, len(self) - 1, keep).round().astype(np.int64))


def windows(trajectories: Sequence[Trajectory], n_pairs: int, overlap: int = 0, frame: str = "world") -> Samples:
    """Every window of ``n_pairs`` consecutive pairs (consecutive windows share ``overlap`` pairs)."""
    if not trajectories:
        raise DataError("no trajectories to sample from (is this split empty?)")
    frames, labels, owner, starts = [], [], [], []
    for ti, t in enumerate(trajectories):
        rel = relative_labels(t, frame).astype(np.float32)
        fidx = np.asarray(t.frame_index, dtype=np.int64)
        for s in window_starts(t.n_pairs, n_pairs, overlap):
            frames.append(fidx[s: s + n_pairs + 1])
            labels.append(rel[s: s + n_pairs])
            owner.append(ti)
            starts.append(s)
    skipped = sum(1 for t in trajectories if t.n_pairs < n_pairs)
    if not frames:
        longest = max(t.n_frames for t in trajectories)
        raise DataError(f"no trajectory has {n_pairs + 1} frames for a window of {n_pairs} pairs "
                        f"(longest: {longest} frames); lower data.window")
    return Samples(np.stack(frames), np.stack(labels), np.asarray(owner, dtype=np.int64),
                   np.asarray(starts, dtype=np.int64), tuple(t.key for t in trajectories), skipped)


class BatchOrder:
    """Shuffled epochs of ``n`` samples in batches of ``batch``; batch ``i`` depends only on (seed, i).

    An epoch is ``n // batch`` full batches (the incomplete rest is dropped so
    BatchNorm never sees a batch of one); with ``n < batch`` an epoch is one
    batch of all ``n`` samples.
    """

    def __init__(self, n: int, batch: int, seed: int) -> None:
        if n < 1:
            raise DataError("no training samples")
        self.n, self.batch, self.seed = n, min(batch, n), seed
        self.per_epoch = max(1, n // self.batch)
        self._epoch, self._perm = -1, np.arange(n)

    def epoch_of(self, i: int) -> int:
        return i // self.per_epoch

    def __call__(self, i: int) -> np.ndarray:
        epoch, k = divmod(i, self.per_epoch)
        if epoch != self._epoch:
            self._perm = np.random.default_rng([self.seed, epoch]).permutation(self.n)
            self._epoch = epoch
        return self._perm[k * self.batch: (k + 1) * self.batch]


DEVICE_BUDGET = 0.4  # of a GPU's free memory the frame caches on it may take: the rest is activations


def _fits_on_device(nbytes: int, device: torch.device, share: int = 1) -> bool:
    """Whether the cache fits this process's part of the device budget.

    ``share`` processes pinned to one GPU (``sweep --per-gpu K``) start at about
    the same time and each measures the free memory before any has allocated,
    so each may take ``1/K`` of the budget: their K copies together stay within
    it whatever the order in which they measure (sharing one copy between
    processes would need CUDA IPC handles kept alive by a producer process).
    """
    if device.type != "cuda":
        return False
    free, _ = torch.cuda.mem_get_info(device)
    return nbytes < DEVICE_BUDGET * free / max(1, share)


class FrameSource:
    """uint8 frames of the cache on ``device``, gathered by global frame index.

    ``resident``: ``auto`` copies the whole cache into device memory when it
    takes under 40 % of the free CUDA memory divided by ``share`` (the
    processes sharing the GPU), ``yes`` always — on any device, the CPU
    included, which is how CI runs the device-resident path — ``no`` never
    (each batch is read from the memory map, then copied through pinned memory
    without blocking on CUDA; on the CPU the memory map is read directly).
    """

    def __init__(self, cache: FrameCache, device: torch.device | str = "cpu", resident: str = "auto",
                 share: int = 1) -> None:
        self.cache, self.device = cache, torch.device(device)
        nbytes = int(np.prod(cache.shape))
        on_device = resident == "yes" or (resident == "auto" and _fits_on_device(nbytes, self.device, share))
        # A copy (the memory map is read-only, and on the CPU ``.to`` would not copy): the bank is the cache in memory.
        self.bank = torch.from_numpy(np.array(cache.array)).to(self.device) if on_device else None

    @property
    def resident(self) -> bool:
        return self.bank is not None

    def __call__(self, frame_index: np.ndarray) -> torch.Tensor:
        idx = np.asarray(frame_index, dtype=np.int64)
        if self.bank is not None:
            flat = torch.from_numpy(idx.reshape(-1)).to(self.device, non_blocking=True)
            return self.bank.index_select(0, flat).view(*idx.shape, *self.bank.shape[1:])
        frames = torch.from_numpy(self.cache.take(idx.reshape(-1)).reshape(*idx.shape, *self.cache.shape[1:]))
        if self.device.type == "cuda":
            return frames.pin_memory().to(self.device, non_blocking=True)
        return frames


@dataclass(frozen=True)
class Photometric:
    """Photometric augmentation on the device (the poses stay valid: the geometry is untouched).

    One brightness shift, contrast factor and gamma per sample (shared by its
    frames, like a change of the bronchoscope's gain), Gaussian noise per pixel.
    """

    brightness: float = 0.1  # additive shift ~ U(-b, b)
    contrast: float = 0.2  # factor about the sample's mean ~ U(1-c, 1+c)
    gamma: float = 0.2  # exponent exp(U(-g, g))
    noise: float = 0.02  # std of additive Gaussian noise

    def __call__(self, frames: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """uint8 ``[B, T, 3, H, W]`` -> augmented uint8 of the same shape, drawn from ``generator``."""
        b = frames.shape[0]
        shape = (b,) + (1,) * (frames.ndim - 1)

        def uniform(lo: float, hi: float) -> torch.Tensor:
            u = torch.rand(shape, generator=generator, device=frames.device)
            return lo + (hi - lo) * u

        x = frames.float().div_(255.0)
        x = x.pow(torch.exp(uniform(-self.gamma, self.gamma)))
        mean = x.mean(dim=tuple(range(1, x.ndim)), keepdim=True)
        x = (x - mean) * uniform(1 - self.contrast, 1 + self.contrast) + mean
        x = x + uniform(-self.brightness, self.brightness)
        if self.noise > 0:
            x = x + self.noise * torch.randn(x.shape, generator=generator, device=x.device)
        return x.clamp_(0.0, 1.0).mul_(255.0).add_(0.5).to(torch.uint8)
