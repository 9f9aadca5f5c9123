"""Shared measurements of bench_train.py (CPU) and bench_gpu.py (GPU): the bare step against the engine.

* **bare step**: what one optimiser step costs with nothing around it — a
  fixed uint8 batch already on the device, ``PoseRegressor`` forward (input
  normalisation included), the pose loss, backward, fused Adam — the same
  maths as training, timed over many steps after warm-up.
* **engine**: ``training.loop.Trainer.fit`` as a run uses it — batches drawn
  by ``BatchOrder`` and gathered by ``FrameSource`` (frames in device memory
  when they fit), the learning-rate schedule, the device-side loss and
  non-finite bookkeeping, validation with BatchNorm re-estimation every
  ``val_every`` steps — over a synthetic frame cache of the given size.

Both count image pairs per second; every architecture takes the same pairs
per step (``batch`` pairs: pairwise models that many pairs, temporal models
``batch / 10`` windows of 10).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bronchocli.data.batches import FrameSource, Samples
from bronchocli.data.cache import FrameCache
from bronchocli.models import build_model
from bronchocli.training.loop import Settings, Trainer
from bronchocli.training.network import PoseRegressor

WINDOW = 10


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def network(arch: str, size: int, device: torch.device) -> PoseRegressor:
    model = build_model(arch, image_size=size).to(memory_format=torch.channels_last)
    return PoseRegressor(model, (0.5,) * 3, (0.25,) * 3, standardized=True).to(device)


def settings(steps: int, batch: int, precision: str, val_every: int, bn_recalibrate: int) -> Settings:
    return Settings(steps=steps, micro_pairs=batch, accum=1, chunk=WINDOW, val_every=val_every, patience=None,
                    min_delta=0.0, lr=1e-4, weight_decay=0.0, warmup_steps=0, schedule="constant", rot_loss="ce",
                    rot_weight=1.0, precision=precision, bn_recalibrate=bn_recalibrate, augment=False, seed=0)


def autocast(device: torch.device, precision: str):
    if precision == "32":
        return torch.autocast(device.type, enabled=False)
    return torch.autocast(device.type, dtype=torch.bfloat16 if precision == "bf16-mixed" else torch.float16)


def bare_step_rate(arch: str, size: int, batch: int, device: torch.device, precision: str, seconds: float,
                   compile: bool = False) -> float:
    """Pairs/s of bare optimiser steps on a fixed batch already on the device."""
    net = network(arch, size, device)
    fwd = torch.compile(net) if compile else net
    n = WINDOW if net.temporal else 1
    b = batch // n
    frames = torch.randint(0, 256, (b, n + 1, 3, size, size), dtype=torch.uint8, device=device)
    labels = torch.randn(b, n, 6, device=device)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4, fused=device.type in ("cuda", "cpu"))
    net.train()

    def step() -> None:
        with autocast(device, precision):
            out, _ = fwd(frames)
        loss = net.loss(out.float(), labels, "ce", 1.0)
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    for _ in range(3):
        step()
    _sync(device)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or steps < 3:
        step()
        steps += 1
        if device.type == "cuda" and steps % 10 == 0:
            _sync(device)
    _sync(device)
    return steps * b * n / (time.perf_counter() - t0)


@dataclass
class EngineResult:
    pairs_per_s: float
    steps: int
    train_s: float
    val_s: float
    resident: bool
    peak_mb: float


def synthetic_cache(root: Path, frames: int, size: int) -> FrameCache:
    rng = np.random.default_rng(0)
    arr = rng.integers(0, 256, (frames, 3, size, size), dtype=np.uint8)
    path = root / f"frames-{frames}-{size}.npy"
    np.save(path, arr)
    return FrameCache(path, arr.shape)


def synthetic_samples(n_frames: int, n_pairs: int, count: int, seed: int) -> Samples:
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, n_frames - n_pairs - 1, count)
    frames = starts[:, None] + np.arange(n_pairs + 1)[None]
    labels = rng.normal(0, 1, (count, n_pairs, 6)).astype(np.float32)
    return Samples(frames, labels, np.zeros(count, dtype=np.int64), np.zeros(count, dtype=np.int64), ("t",))


def engine_rate(arch: str, size: int, batch: int, device: torch.device, precision: str, steps: int,
                val_every: int = 100, bn_recalibrate: int = 16, n_frames: int = 2496,
                compile: bool = False, log_every: int = 0, on_curves=None) -> EngineResult:
    """Pairs/s of ``Trainer.fit`` for ``steps`` optimiser steps over a synthetic cache of ``n_frames`` frames."""
    with tempfile.TemporaryDirectory() as tmp:
        cache = synthetic_cache(Path(tmp), n_frames, size)
        net = network(arch, size, device)
        n = WINDOW if net.temporal else 1
        train = synthetic_samples(n_frames, n, max(64, 1500 // n), seed=1)
        val = synthetic_samples(n_frames, n, max(8, 300 // n), seed=2)
        source = FrameSource(cache, device)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        s = dataclasses.replace(settings(steps, batch, precision, val_every, bn_recalibrate), log_every=log_every)
        trainer = Trainer(net, train, val, source, s, device=device, compile=compile, on_curves=on_curves)
        fit = trainer.fit()
        peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else float("nan")
        return EngineResult(fit.pairs_seen / fit.train_time_s, fit.steps, fit.train_time_s, fit.val_time_s,
                            source.resident, peak)
