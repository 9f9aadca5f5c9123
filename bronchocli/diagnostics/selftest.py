"""`bronchopose selftest`: prove the training engine on this machine's device in about a minute.

What a user runs first on a new GPU box or cluster node. Every check trains
the real networks through the real loop (``training.loop.Trainer``, frames
gathered from a device-resident ``FrameSource``) on synthetic frames, small
enough to be quick anywhere:

* **environment**: torch, CUDA and cuDNN versions, the visible devices, free
  memory, bf16 support, the precision the run uses;
* **train <arch>** for every architecture: a short training on a fixed set of
  synthetic samples in the chosen precision; the training loss must go down
  and stay finite, and (16-mixed) no step may be skipped;
* **resume**: a run saved half-way, then resumed with a different number of
  visible devices (faked: 8 at save, 1 at resume, as a cluster requeue does),
  ends with the same weights as the run that was never interrupted (bitwise on
  the CPU; within 1e-5 relative on CUDA, whose kernels need not be deterministic);
* **cuda vs cpu** (CUDA only): the same network and frames on both devices, the
  fp32 forward with TF32 off within :data:`FP32_TOLERANCE`, bf16 autocast
  within :data:`BF16_TOLERANCE` (relative to the largest output);
* **throughput**: engine pairs/s (training steps of the loop) against the bare
  step (forward, loss, backward, fused Adam on a batch already on the device).
"""

from __future__ import annotations

import copy
import math
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from .. import runkeys
from ..data.batches import FrameSource, Samples
from ..data.cache import FrameCache
from ..errors import BronchoError
from ..models import ARCHITECTURES, build_model
from ..training import checkpoint
from ..training.device import DeviceUnavailable, exact_fp32, seed_everything
from ..training.loop import Settings, Trainer
from ..training.network import PoseRegressor

SIZE = 32  # px: the smallest input every architecture's head accepts unchanged in shape
PAIRS = 4  # image pairs per optimiser step: 4 pairs, or 2 windows of WINDOW pairs
WINDOW = 2
STEPS = 8
FP32_TOLERANCE = 2e-4  # CUDA fp32 (TF32 off) vs CPU: reduction order only (~1e-6); TF32 alone gives ~1.6e-3
BF16_TOLERANCE = 5e-2  # bf16 autocast vs CPU fp32: an 8-bit mantissa through ~100 layers
PRECISIONS = ("auto", "32", "bf16-mixed", "16-mixed")


@dataclass
class Check:
    name: str
    ok: bool
    detail: str
    seconds: float = 0.0


def resolve_device(flag: str) -> torch.device:
    """``auto``: CUDA when there is one, else the CPU; ``cuda`` without CUDA is a one-line error (exit 2)."""
    if flag not in ("auto", "cpu", "cuda"):
        raise BronchoError(f"--device {flag!r}: must be auto, cpu or cuda")
    if flag == "cuda" and not torch.cuda.is_available():
        raise DeviceUnavailable(f"--device cuda: torch {torch.__version__} sees no CUDA device on this machine "
                                f"(built for CUDA {torch.version.cuda or 'none'})")
    return torch.device("cuda" if flag == "cuda" or (flag == "auto" and torch.cuda.is_available()) else "cpu")


def resolve_precision(flag: str, device: torch.device) -> str:
    if flag not in PRECISIONS:
        raise BronchoError(f"--precision {flag!r}: must be one of {', '.join(PRECISIONS)}")
    if flag != "auto":
        return flag
    if device.type == "cuda":
        return "bf16-mixed" if torch.cuda.is_bf16_supported() else "16-mixed"
    return "32"


def environment(device: torch.device, precision: str) -> list[tuple[str, str]]:
    """What the self-test sees: (what, value) rows."""
    rows = [("torch", torch.__version__), ("CUDA (torch build)", torch.version.cuda or "none"),
            ("cuDNN", str(torch.backends.cudnn.version()) if torch.backends.cudnn.is_available() else "none"),
            ("CPU threads", str(torch.get_num_threads()))]
    if torch.cuda.is_available():
        for i in range(torch.cuda.device_count()):
            free, total = torch.cuda.mem_get_info(i)
            rows.append((f"cuda:{i}", f"{torch.cuda.get_device_name(i)}; {free / 2**30:.1f} of "
                                      f"{total / 2**30:.1f} GiB free"))
        rows.append(("bf16 supported", "yes" if torch.cuda.is_bf16_supported() else "no"))
    else:
        rows.append(("CUDA devices", "none"))
    rows += [("device used", str(device)), ("precision", precision)]
    return rows


# -- synthetic data and the trainer -----------------------------------------------------------------------


def synthetic_cache(root: Path, frames: int = 24, size: int = SIZE, seed: int = 0) -> FrameCache:
    rng = np.random.default_rng(seed)
    arr = rng.integers(0, 256, (frames, 3, size, size), dtype=np.uint8)
    path = root / "selftest-frames.npy"
    np.save(path, arr)
    return FrameCache(path, arr.shape)


def synthetic_samples(n: int, pairs: int, frames: int, seed: int) -> Samples:
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, frames - pairs - 1, n)
    idx = starts[:, None] + np.arange(pairs + 1)[None]
    labels = rng.normal(0, 1, (n, pairs, 6)).astype(np.float32)
    zeros = np.zeros(n, dtype=np.int64)
    return Samples(idx, labels, zeros, zeros, ("synthetic",))


def network(arch: str, device: torch.device, size: int = SIZE) -> PoseRegressor:
    model = build_model(arch, image_size=size, dropout=0.0).to(memory_format=torch.channels_last)
    return PoseRegressor(model, (0.5,) * 3, (0.25,) * 3, standardized=True).to(device)


def trainer(arch: str, device: torch.device, precision: str, cache: FrameCache, steps: int = STEPS,
            ckpt_dir: Path | None = None, seed: int = 0, init_seed: int | None = None) -> Trainer:
    """A trainer of ``arch`` on a fixed set of synthetic samples (one batch: the loss must fall)."""
    seed_everything(seed if init_seed is None else init_seed)
    net = network(arch, device, cache.shape[-1])
    pairs = WINDOW if ARCHITECTURES[arch].temporal else 1
    per_step = PAIRS // pairs
    train = synthetic_samples(per_step, pairs, len(cache), seed=1)
    val = synthetic_samples(per_step, pairs, len(cache), seed=2)
    s = Settings(steps=steps, micro_pairs=PAIRS, accum=1, chunk=pairs, val_every=max(1, steps // 2), patience=None,
                 min_delta=0.0, lr=1e-3, weight_decay=0.0, warmup_steps=0, schedule="constant", rot_loss="mse",
                 rot_weight=1.0, precision=precision, bn_recalibrate=1, augment=False, seed=seed)
    return Trainer(net, train, val, FrameSource(cache, device, "yes"), s, device=device, ckpt_dir=ckpt_dir)


def _timed(name: str, fn: Callable[[], tuple[bool, str]]) -> Check:
    t0 = time.perf_counter()
    try:
        ok, detail = fn()
    except Exception as exc:  # noqa: BLE001 - a self-test reports every failure as a row, never a traceback
        ok, detail = False, f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    return Check(name, ok, detail, time.perf_counter() - t0)


# -- the checks -----------------------------------------------------------------------------------------------


def check_training(arch: str, device: torch.device, precision: str, cache: FrameCache) -> tuple[bool, str]:
    t = trainer(arch, device, precision, cache)
    fit = t.fit()
    first, last = fit.history[0][runkeys.TRAIN_LOSS], fit.history[-1][runkeys.TRAIN_LOSS]
    finite = all(math.isfinite(h[runkeys.TRAIN_LOSS]) and math.isfinite(h[runkeys.VAL_LOSS]) for h in fit.history)
    ok = finite and last < first and t.skipped_steps == 0
    skipped = f", {t.skipped_steps} steps skipped by the loss scaler" if t.skipped_steps else ""
    rate = fit.pairs_seen / max(fit.train_time_s, 1e-9)
    return ok, f"train loss {first:.3g} -> {last:.3g} over {fit.steps} steps{skipped}; {rate:.0f} pairs/s"


@contextmanager
def visible_devices(count: int) -> Iterator[None]:
    """Pretend ``count`` CUDA devices are visible (what a resume on another node or Slurm allocation sees)."""
    real = torch.cuda.device_count
    torch.cuda.device_count = lambda: count  # type: ignore[assignment]
    try:
        yield
    finally:
        torch.cuda.device_count = real  # type: ignore[assignment]


@contextmanager
def reproducible(device: torch.device) -> Iterator[None]:
    """On CUDA: fp32 without TF32 and deterministic cuDNN algorithms inside the block (nothing changes on a CPU).

    Measured on an H200 (benchmarks/README.md, "GPU device check"): two identical 2-step bf16 runs of ConvLSTM
    from the same seed already differ (validation loss 1.73 vs 1.58, BatchNorm running variances by 10-16),
    with cuDNN's deterministic algorithms too; in fp32 with deterministic cuDNN they agree to 4e-8. So a
    save -> resume comparison is only meaningful where two straight runs agree: there it proves the state.
    """
    if device.type != "cuda":
        yield
        return
    saved = torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark
    torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
    try:
        with exact_fp32():
            yield
    finally:
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = saved


def check_resume(arch: str, device: torch.device, precision: str, cache: FrameCache, tmp: Path) -> tuple[bool, str]:
    """Save at step 2 of 4 seeing 8 devices, resume seeing 1: the final weights must equal an uninterrupted run's.

    On CUDA in fp32 with deterministic cuDNN (``reproducible``): mixed precision makes two uninterrupted runs
    differ already, which would hide what this check is for (the training state round-trips).
    """
    steps = 4
    if device.type == "cuda":
        precision = "32"
    with reproducible(device):
        straight = trainer(arch, device, precision, cache, steps=steps)
        straight.fit()
        first = trainer(arch, device, precision, cache, steps=steps, ckpt_dir=tmp)
        first.s = replace(first.s, steps=steps // 2)  # stop half-way, as a preemption would (checkpoint at step 2)
        with visible_devices(8):
            first.fit()
        with visible_devices(1):
            state = checkpoint.load(tmp / "last.pt")  # weights_only, as a real resume
            second = trainer(arch, device, precision, cache, steps=steps, init_seed=123)  # load_state must undo it
            second.load_state(state)
            second.fit()
    a, b = straight.net.state_dict(), second.net.state_dict()
    diff = max((a[k].double() - b[k].double()).abs().max().item() for k in a if a[k].is_floating_point())
    scale = max(a[k].double().abs().max().item() for k in a if a[k].is_floating_point())
    exact = all(torch.equal(a[k], b[k]) for k in a)
    ok = exact or (device.type == "cuda" and diff <= 1e-5 * scale)
    how = "bitwise identical" if exact else f"max |difference| {diff:.2g} (of {scale:.3g})"
    where = " (fp32, deterministic cuDNN)" if device.type == "cuda" else ""
    return ok, f"saved at step 2 of 4 seeing 8 devices, resumed seeing 1{where}: final weights {how}"


@dataclass
class Agreement:
    fp32_error: float
    bf16_error: float
    scale: float

    @property
    def fp32_tolerance(self) -> float:
        return FP32_TOLERANCE * self.scale

    @property
    def bf16_tolerance(self) -> float:
        return BF16_TOLERANCE * self.scale

    @property
    def ok(self) -> bool:
        return self.fp32_error <= self.fp32_tolerance and self.bf16_error <= self.bf16_tolerance


@torch.no_grad()
def device_agreement(net: PoseRegressor, device: torch.device, size: int = SIZE, seed: int = 0) -> Agreement:
    """``net`` (eval mode) on the CPU in fp32 against ``device``: fp32 with TF32 off, and bf16 autocast."""
    gen = torch.Generator().manual_seed(seed)
    frames = torch.randint(0, 256, (2, 4, 3, size, size), dtype=torch.uint8, generator=gen)
    cpu_net = copy.deepcopy(net).to("cpu").eval()
    reference, _ = cpu_net(frames)
    net = net.to(device).eval()
    with exact_fp32():
        fp32, _ = net(frames.to(device))
    with torch.autocast(device.type, dtype=torch.bfloat16):
        bf16, _ = net(frames.to(device))
    scale = reference.abs().max().item() + 1e-6
    return Agreement((fp32.float().cpu() - reference).abs().max().item(),
                     (bf16.float().cpu() - reference).abs().max().item(), scale)


def check_agreement(arch: str, device: torch.device) -> tuple[bool, str]:
    seed_everything(0)
    a = device_agreement(network(arch, torch.device("cpu")).eval(), device)
    return a.ok, (f"fp32 (TF32 off) {a.fp32_error / a.scale:.1e} of the output scale (limit {FP32_TOLERANCE:.0e}); "
                  f"bf16 {a.bf16_error / a.scale:.1e} (limit {BF16_TOLERANCE:.0e})")


def bare_step_rate(arch: str, device: torch.device, precision: str, cache: FrameCache, steps: int = 4) -> float:
    """Pairs/s of bare optimiser steps (forward, loss, backward, fused Adam) on a batch already on the device."""
    t = trainer(arch, device, precision, cache, steps=steps)
    frames = t.source(t.train_set.frames)
    labels = torch.from_numpy(t.train_set.labels).to(device)

    def step() -> None:
        with t.autocast():
            out, _ = t.net(frames)
        t.scaler.scale(t.net.loss(out.float(), labels, "mse", 1.0)).backward()
        t.scaler.step(t.opt)
        t.scaler.update()
        t.opt.zero_grad(set_to_none=True)

    t.net.train()
    step()
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    _sync(device)
    return steps * PAIRS / (time.perf_counter() - t0)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def check_throughput(arch: str, device: torch.device, precision: str, cache: FrameCache) -> tuple[bool, str]:
    bare = bare_step_rate(arch, device, precision, cache)
    t = trainer(arch, device, precision, cache, steps=6)
    t.s = replace(t.s, val_every=6, bn_recalibrate=0)
    t._train_until(1)  # warm-up step, then time the loop's steps alone
    _sync(device)
    t0 = time.perf_counter()
    t._train_until(6)
    _sync(device)
    engine = 5 * PAIRS / (time.perf_counter() - t0)
    return True, (f"{arch}: engine {engine:.0f} pairs/s, bare step {bare:.0f} pairs/s "
                  f"({engine / bare:.0%} of the bare step)")


def run(device: torch.device, precision: str, archs: Sequence[str] | None = None,
        on_check: Callable[[Check], None] | None = None) -> list[Check]:
    """Every check in order; ``on_check`` sees each as it finishes."""
    archs = list(archs or ARCHITECTURES)
    checks: list[Check] = []

    def add(check: Check) -> None:
        checks.append(check)
        if on_check is not None:
            on_check(check)

    with tempfile.TemporaryDirectory(prefix="bronchopose-selftest-") as tmp:
        root = Path(tmp)
        cache = synthetic_cache(root)
        for arch in archs:
            add(_timed(f"train {arch}", lambda a=arch: check_training(a, device, precision, cache)))
        ckpt = root / "ckpt"
        ckpt.mkdir()
        # convlstm: recurrent state and a ConvLSTM cell, the most to restore
        resumed = "convlstm" if "convlstm" in archs else archs[0]
        add(_timed(f"resume {resumed}", lambda: check_resume(resumed, device, precision, cache, ckpt)))
        if device.type == "cuda":
            for arch in archs:
                add(_timed(f"cuda vs cpu {arch}", lambda a=arch: check_agreement(a, device)))
        add(_timed("throughput", lambda: check_throughput(archs[0], device, precision, cache)))
    return checks
