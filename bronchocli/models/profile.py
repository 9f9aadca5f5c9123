"""Parameters, MACs, latency and peak memory per architecture: the paper's ablation table.

``profile_arch(name, image_size, device, batch, repeats)`` builds a model in
eval mode and measures, on random normalised frames:

* ``params``: every parameter of the model (BN statistics excluded).
* ``gmacs_per_pair``: multiply-accumulates of one forward over a window of
  ``window`` pairs (``window + 1`` frames, batch 1) divided by ``window``.
  Convolutions, linear layers and matrix products are counted with
  ``torch.utils.flop_counter.FlopCounterMode`` (MACs = FLOPs / 2); its registry
  has no recurrent ops, so ``nn.LSTM`` layers are counted analytically
  (``4·hidden·(input + hidden)`` per step and layer) and whatever the counter
  saw inside them is discarded. Element-wise work (BN, activations, pooling)
  is not counted, as usual for GMAC figures.
* ``latency_ms_b1`` / ``latency_ms_bN``: median wall time of one forward over
  ``repeats`` timed runs after ``warmup`` untimed ones, divided by the pairs it
  processed (batch · window), with batch 1 and batch N. Every architecture gets
  the same input, a window of ``window`` pairs per forward (temporal models
  need one; for per-pair models it is simply more pairs), so the per-pair
  figures compare like with like. Recurrent models start each window from an
  empty state (carrying it costs the same).
* ``peak_mem_mb``: memory allocated above the resting model (weights, buffers)
  during one batch-N forward. CUDA: ``max_memory_allocated`` minus what was
  allocated before. CPU: the peak of the bytes of live tensors created during
  the forward, tracked op by op through a ``TorchDispatchMode`` (the process's
  RSS is useless here: the C allocator keeps freed memory resident). Library
  workspaces that are not tensors are not seen. ``weights_mb`` is the size of
  parameters and buffers.

Everything runs under ``torch.inference_mode`` with the requested autocast
precision; the MAC count always runs without autocast (it does not depend on
precision).
"""

from __future__ import annotations

import contextlib
import statistics
import time
import weakref
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves
from torch.utils.flop_counter import FlopCounterMode

from ..errors import BronchoError
from . import ARCHITECTURES, PoseNet, build_model, n_params

PRECISIONS = ("32", "16-mixed", "bf16-mixed")
DEVICES = ("cpu", "cuda")


def resolve_device(device: str) -> torch.device:
    """``cpu`` or ``cuda`` (the current CUDA device), or a BronchoError saying why not."""
    if device not in DEVICES:
        raise BronchoError(f"--device {device!r}: must be one of {', '.join(DEVICES)}")
    if device == "cuda" and not torch.cuda.is_available():
        raise BronchoError(
            f"--device cuda: CUDA is not available (torch {torch.__version__}, "
            f"built with CUDA {torch.version.cuda or 'none'}); use --device cpu"
        )
    return torch.device("cuda", torch.cuda.current_device()) if device == "cuda" else torch.device("cpu")


def set_threads(threads: int) -> None:
    """Set torch's CPU threads (``--threads``)."""
    if threads < 1:
        raise BronchoError(f"--threads {threads}: must be at least 1")
    torch.set_num_threads(threads)


def autocast(device: torch.device, precision: str) -> contextlib.AbstractContextManager:
    if precision not in PRECISIONS:
        raise BronchoError(f"--precision {precision!r}: must be one of {', '.join(PRECISIONS)}")
    if precision == "32":
        return contextlib.nullcontext()
    if precision == "16-mixed" and device.type == "cpu":
        raise BronchoError("--precision 16-mixed needs --device cuda (use bf16-mixed on CPU)")
    dtype = torch.float16 if precision == "16-mixed" else torch.bfloat16
    return torch.autocast(device_type=device.type, dtype=dtype)


def random_frames(batch: int, window: int, image_size: int, device: torch.device, seed: int = 0) -> torch.Tensor:
    """Normalised-looking frames ``[batch, window + 1, 3, S, S]`` (standard normal)."""
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(batch, window + 1, 3, image_size, image_size, generator=gen).to(device)


# -- MACs -----------------------------------------------------------------------


def _lstm_macs(module: nn.LSTM, inputs: tuple, counter: list[int]) -> None:
    x = inputs[0]
    steps = x.shape[0] * x.shape[1] if x.ndim == 3 else x.shape[0]  # (batch and) time
    size_in, hidden = module.input_size, module.hidden_size
    dirs = 2 if module.bidirectional else 1
    for _ in range(module.num_layers):
        counter[0] += steps * dirs * 4 * hidden * (size_in + hidden)
        size_in = hidden * dirs


def count_macs(model: nn.Module, frames: torch.Tensor) -> int:
    """Multiply-accumulates of ``model(frames)`` (see the module doc for what is counted)."""
    lstm_macs = [0]
    lstms = {name: m for name, m in model.named_modules() if isinstance(m, nn.LSTM)}
    hooks = [m.register_forward_pre_hook(lambda mod, inp: _lstm_macs(mod, inp, lstm_macs)) for m in lstms.values()]
    try:
        with torch.inference_mode(), FlopCounterMode(display=False) as counter:
            model(frames)
    finally:
        for h in hooks:
            h.remove()
    counts = counter.get_flop_counts()
    root = type(model).__name__
    flops = counter.get_total_flops()
    flops -= sum(sum(counts.get(f"{root}.{name}", {}).values()) for name in lstms)  # counted analytically
    return flops // 2 + lstm_macs[0]


# -- time and memory ------------------------------------------------------------------


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_forward(model: PoseNet, frames: torch.Tensor, repeats: int, warmup: int, precision: str,
                 spread: list[float] | None = None) -> float:
    """Median seconds of one forward over ``repeats`` runs after ``warmup`` untimed ones; ``spread`` receives
    (slowest - fastest) / median of the timed runs (how precise the median is)."""
    device = frames.device
    times = []
    with torch.inference_mode(), autocast(device, precision):
        for i in range(warmup + repeats):
            _sync(device)
            start = time.perf_counter()
            model(frames)
            _sync(device)
            if i >= warmup:
                times.append(time.perf_counter() - start)
    median = statistics.median(times)
    if spread is not None:
        spread.append((max(times) - min(times)) / median if median > 0 else 0.0)
    return median


class _LiveTensorBytes(TorchDispatchMode):
    """Track the bytes of tensor storages created inside the mode and still alive; keep the peak.

    Every op's output storage is recorded once (views and in-place results
    share a recorded storage) and released by a weakref finalizer when its last
    tensor dies, so ``peak`` is the CPU analogue of CUDA's max_memory_allocated
    for what the forward allocates (allocator overhead and library-internal
    workspaces are not tensors and are not seen).
    """

    def __init__(self) -> None:
        super().__init__()
        self.live = self.peak = 0
        self._alive: set[int] = set()

    def _release(self, key: int, nbytes: int) -> None:
        self._alive.discard(key)
        self.live -= nbytes

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in tree_leaves(out):
            if isinstance(t, torch.Tensor):
                storage = t.untyped_storage()
                key, nbytes = storage.data_ptr(), storage.nbytes()
                if nbytes and key not in self._alive:
                    self._alive.add(key)
                    self.live += nbytes
                    self.peak = max(self.peak, self.live)
                    weakref.finalize(storage, self._release, key, nbytes)
        return out


def peak_memory(model: PoseNet, frames: torch.Tensor, precision: str) -> tuple[int, str]:
    """Bytes allocated above the resting model during one forward, and how that was measured."""
    device = frames.device
    with torch.inference_mode(), autocast(device, precision):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
            torch.cuda.reset_peak_memory_stats(device)
            before = torch.cuda.memory_allocated(device)
            model(frames)
            torch.cuda.synchronize(device)
            return torch.cuda.max_memory_allocated(device) - before, "CUDA max_memory_allocated above resting"
        with _LiveTensorBytes() as tracker:
            model(frames)
    return tracker.peak, "peak live tensor bytes (dispatch tracker)"


# -- the table ---------------------------------------------------------------------


def _device_label(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    return f"cpu ({torch.get_num_threads()} threads)"


def profile_arch(
    name: str,
    image_size: int = 256,
    device: str = "cpu",
    batch: int = 8,
    repeats: int = 10,
    *,
    window: int = 10,
    warmup: int = 2,
    precision: str = "32",
    channels_last: bool = True,
    batch_n: bool = True,
) -> dict[str, Any]:
    """One row of the ablation table for architecture ``name`` (keys documented in docs/models.md);
    ``batch_n=False`` times batch 1 only (no batch-N latency, no peak memory: what the report's table shows)."""
    limits = (("--batch", batch, 1), ("--repeats", repeats, 1), ("--window", window, 1), ("--warmup", warmup, 0))
    for flag, value, low in limits:
        if value < low:
            raise BronchoError(f"{flag} {value}: must be at least {low}")
    dev = resolve_device(device)
    autocast(dev, precision)  # validates the precision for this device before any work
    model = build_model(name, image_size=image_size).eval().to(dev)
    if channels_last:
        model.to(memory_format=torch.channels_last)
    one = random_frames(1, window, image_size, dev)
    macs = count_macs(model, one)  # its forward doubles as a warm-up of the batch-1 timing
    many = random_frames(batch, window, image_size, dev, seed=1) if batch_n else None
    spread: list[float] = []
    t1 = time_forward(model, one, repeats, warmup, precision, spread)
    if batch_n:
        tn = time_forward(model, many, repeats, warmup, precision)
        peak, method = peak_memory(model, many, precision)
    else:
        tn, peak, method = None, None, "not measured"
    weights = sum(t.numel() * t.element_size() for t in list(model.parameters()) + list(model.buffers()))
    params = n_params(model)
    return {
        "arch": name,
        "image_size": image_size,
        "device": _device_label(dev),
        "precision": precision,
        "channels_last": channels_last,
        "window": window,
        "batch": batch,
        "params": params,
        "params_m": round(params / 1e6, 3),
        "gmacs_per_pair": macs / window / 1e9,
        "latency_ms_b1": t1 / window * 1e3,
        "latency_ms_bN": None if tn is None else tn / (batch * window) * 1e3,
        "repeats": repeats,
        "latency_spread_b1": spread[0],
        "pairs_per_s_bN": None if tn is None else batch * window / tn,
        "peak_mem_mb": None if peak is None else peak / 2**20,
        "weights_mb": weights / 2**20,
        "memory_method": method,
        "torch": torch.__version__,
    }


def arch_names(names: Sequence[str]) -> list[str]:
    """Validated architecture names; ``all`` (alone or among others) means every architecture."""
    names = list(names)
    if "all" in names:
        return list(ARCHITECTURES)
    unknown = [n for n in names if n not in ARCHITECTURES]
    if unknown:
        raise BronchoError(f"--arch {', '.join(unknown)}: unknown (valid: all, {', '.join(ARCHITECTURES)})")
    return list(dict.fromkeys(names))


# (result key, short column title, format); the caption says what the short titles mean.
COLUMNS = (
    ("arch", "arch", "{}"),
    ("params_m", "params M", "{:.3f}"),
    ("gmacs_per_pair", "GMAC", "{:.3f}"),
    ("latency_ms_b1", "ms b1", "{:.2f}"),
    ("latency_ms_bN", "ms bN", "{:.2f}"),
    ("pairs_per_s_bN", "pairs/s bN", "{:.1f}"),
    ("peak_mem_mb", "peak MB bN", "{:.1f}"),
)


def cells(row: dict[str, Any]) -> list[str]:
    """The formatted table cells of one result row (``COLUMNS`` order)."""
    return ["-" if row[key] is None else fmt.format(row[key]) for key, _, fmt in COLUMNS]


def caption(rows: Sequence[dict[str, Any]]) -> str:
    """One line saying how the numbers of ``rows`` were measured."""
    r = rows[0]
    return (
        f"{r['image_size']}x{r['image_size']}, {r['device']}, precision {r['precision']}, "
        f"channels_last {r['channels_last']}, torch {r['torch']}. GMAC: conv/linear multiply-accumulates per "
        f"image pair. ms b1 / ms bN: median of {r.get('repeats', '?')} forward times per pair at batch 1 / "
        f"batch N={r['batch']}, "
        f"a forward being a window of {r['window']} pairs. peak MB bN: {r['memory_method']} above the resting "
        f"model during one batch-N forward"
    )


def markdown_table(rows: Sequence[dict[str, Any]]) -> str:
    head = [title for _, title, _ in COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cells(r)) + " |" for r in rows]
    return "\n".join(lines)
