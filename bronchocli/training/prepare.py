"""Everything a run needs before its first step, from training data only: split, frames, statistics, samples.

``prepare(cfg, cell)`` opens the dataset, splits it for the cell's population,
fold and training-set size, decodes every frame into the cache (a bad frame
fails here, before an MLflow run exists), computes the image normalisation
and label statistics on the training split only, and builds the training and
validation samples (pairs, or windows of pairs for temporal models).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..cells import Cell
from ..config import Config
from ..data.batches import Samples, windows
from ..data.cache import FrameCache, channel_stats, input_size, open_frame_cache
from ..data.gimbal import world_label_warning
from ..data.reader import Dataset, warn_once
from ..data.source import open_dataset
from ..data.splits import Split, limit_train, make_split
from ..errors import ConfigError, DataError
from ..models import ARCHITECTURES


@dataclass(frozen=True)
class RunData:
    dataset: Dataset
    split: Split
    cache: FrameCache
    image_size: int
    image_mean: tuple[float, float, float]
    image_std: tuple[float, float, float]
    label_mean: np.ndarray  # (6,) mean relative pose of the training pairs (the train_mean reference)
    label_std: np.ndarray  # (6,)
    train: Samples
    val: Samples

    @property
    def fingerprint(self) -> str:
        return self.dataset.fingerprint


def sample_pairs(cfg: Config, arch: str) -> int:
    """Image pairs per training sample: 1 for pairwise models, L·K for temporal ones."""
    return cfg.data.window * cfg.train.tbptt_chunks if ARCHITECTURES[arch].temporal else 1


def check_batch(cfg: Config, cell: Cell) -> None:
    """``train.batch_size`` counts image pairs; a temporal model needs whole samples of L·K pairs in it."""
    n = sample_pairs(cfg, cell.arch)
    if cfg.train.batch_size % n:
        raise ConfigError(f"train.batch_size {cfg.train.batch_size}: {cell.arch} trains on samples of {n} image "
                          f"pairs (data.window x train.tbptt_chunks), so the batch must be a multiple of {n}")


def label_stats(samples: Samples) -> tuple[np.ndarray, np.ndarray]:
    """Per-component mean and std of the training labels (std floored so no component divides by ~0)."""
    labels = samples.labels.reshape(-1, 6).astype(np.float64)
    std = labels.std(0)
    return labels.mean(0), np.maximum(std, 1e-3 * max(float(std.max()), 1e-6))


def prepare(cfg: Config, cell: Cell, progress: bool = True) -> RunData:
    check_batch(cfg, cell)
    dataset = open_dataset(cfg)
    if cell.pose_frame == "world" and (gimbal := world_label_warning(dataset)):
        warn_once(gimbal)  # the paper's labels are noise near gimbal lock: say so before training on them
    split = make_split(dataset, cell.population, cell.fold, cfg.splits)
    split = limit_train(split, cell.train_trajectories, cfg.splits.seed)
    cache = open_frame_cache(cfg, dataset, progress=progress)  # decodes every frame: fails early on a bad one
    image_mean, image_std = channel_stats(cache, split.frame_indices("train"))
    n = sample_pairs(cfg, cell.arch)
    overlap = min(cfg.data.overlap, n - 1)
    train = windows(split.train, n, overlap, cell.pose_frame)
    val = windows(split.val, n, overlap, cell.pose_frame).evenly(cfg.train.max_val_pairs)
    if len(train) < 2:
        what = "windows" if n > 1 else "pairs"
        raise DataError(f"{cell.label}: the split gives {len(train)} training {what} of {n} pair(s); need >= 2 "
                        f"(longer trajectories, more trajectories or a smaller data.window)")
    pairs = windows(split.train, 1, 0, cell.pose_frame)  # every training pair, for the label statistics
    mean, std = label_stats(pairs)
    return RunData(dataset, split, cache, input_size(cfg.data.image_size, dataset),
                   tuple(map(float, image_mean)), tuple(map(float, image_std)), mean, std, train, val)
