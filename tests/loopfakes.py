"""Synthetic samples, a frame bank and loop settings for the training-loop tests (no dataset on disk)."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from bronchocli.data.batches import Samples
from bronchocli.training.loop import Settings


class FakeSource:
    """Frames of a fixed random uint8 bank, indexed like FrameSource."""

    def __init__(self, n: int = 40, size: int = 8, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.bank = torch.from_numpy(rng.integers(0, 256, (n, 3, size, size), dtype=np.uint8))

    def __call__(self, idx):
        idx = torch.as_tensor(np.asarray(idx, dtype=np.int64))
        return self.bank[idx.reshape(-1)].view(*idx.shape, *self.bank.shape[1:])


def samples(n: int, seed: int = 1, scale: float = 1.0, pairs: int = 1, frames: int = 40) -> Samples:
    """``n`` samples of ``pairs`` consecutive pairs over a bank of ``frames`` frames, random labels."""
    rng = np.random.default_rng(seed)
    idx = np.stack([np.arange(i, i + pairs + 1) % frames for i in range(n)])
    labels = (rng.normal(0, 1, (n, pairs, 6)) * scale).astype(np.float32)
    return Samples(idx, labels, np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64), ("t",))


def settings(**kw) -> Settings:
    base = dict(steps=6, micro_pairs=4, accum=1, chunk=1, val_every=2, patience=None, min_delta=0.0, lr=1e-2,
                weight_decay=0.0, warmup_steps=0, schedule="constant", rot_loss="mse", rot_weight=1.0,
                precision="32", bn_recalibrate=0, augment=False, seed=0)
    return Settings(**{**base, **kw})


class TinyNet(nn.Module):
    """A pair network small enough for unit tests: conv + BN on both frames, linear head."""

    temporal = False
    recurrent = False

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(6, 4, 3, padding=1)
        self.bn = nn.BatchNorm2d(4)
        self.head = nn.Linear(4, 6)

    def forward(self, x, state=None):
        b, t = x.shape[:2]
        pairs = torch.cat([x[:, 1:], x[:, :-1]], dim=2).reshape(b * (t - 1), 6, *x.shape[-2:])
        z = torch.relu(self.bn(self.conv(pairs))).mean((2, 3))
        return self.head(z).view(b, t - 1, 6), None
