"""`bronchopose profile --speed FILE`: measure each architecture's training speed in every candidate setting
(precision x memory format) and write the fastest one whose numerics hold into a speed settings file.

For every architecture and candidate (fp32 / bf16 autocast where the device runs bf16 natively, channels-last
on / off) the real training loop (``training.loop.Trainer``) trains the same network from the same seed on
the same synthetic samples for ``steps`` optimiser steps:

* **speed**: training pairs/s = pairs per step / the median optimiser-step time (the median leaves out the
  first steps' warm-up, the validations between blocks and a shared machine's hiccups);
* **numerics**: before its first step each training computes one batch's gradients from the common initial
  weights (``training.probe.batch_gradients``, stochastic depth off), and so does the network in float64 (the
  exact function, to ~1e-16). A candidate whose gradients lie as close to those as the default's do, or within
  ``speed.GRAD_TOLERANCE`` (relative L2, :func:`grad_gap`), computes the network's function as exactly and
  qualifies: fp32 in the other memory format, where only the order of the sums differs. Any other candidate
  (bf16, TF32: an error ~100x larger) qualifies when the mean training loss of its blocks of :data:`BLOCK` steps
  differs from the fp32 reference's (the fp32 channels-last run; on CUDA with TF32 off) by at most
  ``speed.LOSS_TOLERANCE`` on average (relative; :func:`loss_gap`), and only when the reference learns in those
  steps (:func:`reference_learns`).

Per architecture the fastest qualifying candidate becomes the setting when it is at least ``speed.MIN_GAIN``
times as fast as the device's default; otherwise the default stays. The samples are a fixed pool of
synthetic frames with random poses, cycled, so the loss falls steadily (the network memorises them) and the
curves have something to track.

With ``frozen`` stages (``--frozen-stages N``, ``--backbone B``) it measures the training a run with a pretrained
backbone frozen up to stage N does: both backbones start from the same weights, their first N stages are computed
once for the pool's frames (``training.frozen_features``) and each step trains the rest; the entry goes under
the device's ``frozen["<B>, frozen <N>"]`` (``speed.frozen_key``), which such runs use first.
"""

from __future__ import annotations

import datetime as dt
import math
import platform
import statistics
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from .. import runkeys, speed
from ..data.batches import FrameSource
from ..data.cache import FrameCache
from ..errors import BronchoError
from ..models import ARCHITECTURES, PAPER_BACKBONE, build_model
from ..models.backbones import StochasticDepth
from ..training.device import bf16_fast, device_key, exact_fp32, seed_everything, set_tf32
from ..training.frozen_features import FeatureSource, load_or_compute
from ..training.loop import Settings, Trainer
from ..training.probe import batch_gradients
from ..training.network import PoseRegressor
from .selftest import synthetic_cache, synthetic_samples

BLOCK = 10  # optimiser steps per compared loss block
# The reference must learn for its curve to check anything: after its first block (where every network fits the
# labels' mean), its last block at most this fraction of its second. A reference that stays flat (the ConvLSTM and
# 3-D-conv heads on a cached random-weight prefix in 50 steps, measured) would let any candidate through, bf16
# included, which on the same prefix keeps the baseline and the LSTM head from learning at all (the shipped file's
# frozen entry): no candidate qualifies then.
MIN_DROP = 0.8
WINDOW = 10  # pairs per temporal sample (data.window's default)
POOL_STEPS = 4  # the sample pool holds this many steps' worth of samples (cycled: the loss keeps falling)


@dataclass
class Trial:
    """One candidate's training of one architecture."""

    precision: str
    channels_last: bool
    pairs_per_s: float
    blocks: list[float]  # mean training loss per block of BLOCK steps
    gap: float = math.nan  # mean relative block difference from the fp32 reference (loss_gap)
    grad_error: float = math.nan  # relative L2 distance of one batch's gradients from float64's (grad_gap)
    exact: bool = False  # grad_error within the default's or speed.GRAD_TOLERANCE
    grads: torch.Tensor | None = None  # those gradients (dropped once compared)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def qualifies(self) -> bool:
        """The network's function as exactly as the default computes it, or a loss curve that tracks the
        reference's."""
        return self.exact or self.gap <= speed.LOSS_TOLERANCE

    @property
    def name(self) -> str:
        return label(self.precision, self.channels_last)


def label(precision: str, channels_last: bool) -> str:
    return f"{'fp32' if precision == '32' else precision.split('-')[0]} {'CL' if channels_last else 'contiguous'}"


def candidates(device: torch.device) -> list[tuple[str, bool]]:
    """The settings worth measuring here: bf16 only where the device runs it natively."""
    precisions = ["32", "bf16-mixed"] if bf16_fast(device) else ["32"]
    return [(p, cl) for p in precisions for cl in (True, False)]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class Baton:
    """Round-robin turns between trainer threads: one optimiser step each in turn, so a shared machine's load
    drifts over every candidate alike (alternating blocks of one step). Only the holder computes."""

    def __init__(self, n: int) -> None:
        self.cond = threading.Condition()
        self.turn, self.alive = 0, list(range(n))

    def wait(self, i: int) -> None:
        with self.cond:
            self.cond.wait_for(lambda: self.turn == i)

    def pass_on(self, i: int, finished: bool = False) -> None:
        with self.cond:
            pos = self.alive.index(i)
            if finished:
                self.alive.remove(i)
            if self.alive:
                self.turn = self.alive[(pos + (0 if finished else 1)) % len(self.alive)]
            self.cond.notify_all()


def _trainer(arch: str, device: torch.device, precision: str, channels_last: bool, cache: FrameCache, *,
             pairs: int, steps: int, seed: int, on_step: Callable[[int, int], None], backbone: str = PAPER_BACKBONE,
             frozen: int = 0) -> Trainer:
    seed_everything(seed)
    # no dropout: no RNG inside a step
    model = build_model(arch, image_size=cache.shape[-1], dropout=0.0, backbone=backbone)
    if frozen:  # as from one pretrained file: both backbones alike, their first stages frozen and computed once
        model.backbone_prev.load_state_dict(model.backbone_cur.state_dict())
        model.freeze_stages(frozen)
    if channels_last:
        model.to(memory_format=torch.channels_last)
    net = PoseRegressor(model, (0.5,) * 3, (0.25,) * 3, standardized=True).to(device)
    source = FrameSource(cache, device, "yes")
    if frozen:
        source = FeatureSource(load_or_compute(net, cache, frozen)[0], device)
        net.model.prefix_cached = frozen
    per_sample = min(WINDOW, pairs) if ARCHITECTURES[arch].temporal else 1
    samples = synthetic_samples(POOL_STEPS * max(1, pairs // per_sample), per_sample, len(cache), seed=1)
    val = synthetic_samples(max(1, pairs // per_sample), per_sample, len(cache), seed=2)
    s = Settings(steps=steps, micro_pairs=pairs, accum=1, chunk=per_sample, val_every=BLOCK, patience=None,
                 min_delta=0.0, lr=1e-3, weight_decay=0.0, warmup_steps=0, schedule="constant", rot_loss="mse",
                 rot_weight=1.0, precision=precision, bn_recalibrate=1, augment=False, seed=seed)
    return Trainer(net, samples, val, source, s, device=device, on_step=on_step)


def train_trials(arch: str, device: torch.device, settings: Sequence[tuple[str, bool]], cache: FrameCache, *,
                 pairs: int, steps: int, seed: int = 0, backbone: str = PAPER_BACKBONE, frozen: int = 0) -> list[Trial]:
    """Train ``arch`` for ``steps`` steps in each setting, the trainings interleaved step by step (see
    :class:`Baton`); each one's step rate and loss per block. A setting ``(precision, cl, tf32)`` with
    ``tf32`` True/False sets CUDA's TF32 switches at each of its turns (they are global)."""
    baton = Baton(len(settings))
    results: list[Trial | BaseException | None] = [None] * len(settings)

    def train(i: int, precision: str, cl: bool, tf32: bool | None = None) -> None:
        durations: list[float] = []
        began = [0.0]

        def my_turn() -> None:
            baton.wait(i)
            if tf32 is not None:
                set_tf32(tf32)
            began[0] = time.perf_counter()

        def stepped(step: int, total: int) -> None:
            _sync(device)
            durations.append(time.perf_counter() - began[0])
            baton.pass_on(i)
            my_turn()

        my_turn()
        try:
            t = _trainer(arch, device, precision, cl, cache, pairs=pairs, steps=steps, seed=seed, on_step=stepped,
                         backbone=backbone, frozen=frozen)
            with no_stochastic_depth(t.net):
                _, grads = batch_gradients(t, 0)  # from the weights every setting starts from (one seed), untimed
            began[0] = time.perf_counter()
            fit = t.fit()
            rate = pairs / statistics.median(durations[1:] or durations)
            results[i] = Trial(precision, cl, rate, [h[runkeys.TRAIN_LOSS] for h in fit.history], grads=grads)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the calling thread
            results[i] = exc
        finally:
            baton.pass_on(i, finished=True)

    threads = [threading.Thread(target=train, args=(i, *st), daemon=True)
               for i, st in enumerate(settings)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for r in results:
        if isinstance(r, BaseException):
            raise r
    return [r for r in results if isinstance(r, Trial)]


def loss_gap(blocks: Sequence[float], reference: Sequence[float]) -> float:
    """How far a loss curve is from the reference: the mean over blocks of their relative difference (inf when
    either is not finite). The mean, not the largest: on memorised random poses even fp32 with another memory
    format (another summation order) drifts ~4 % in single blocks after 50 steps (measured; benchmarks/README.md)."""
    gaps = [abs(a - b) / max(abs(b), 1e-12) for a, b in zip(blocks, reference)]
    if not gaps or not all(math.isfinite(g) for g in gaps):
        return math.inf
    return sum(gaps) / len(gaps)


class _Float64Source:
    """A frame or feature source whose batches come as float64."""

    def __init__(self, source: Callable[[Any], torch.Tensor]) -> None:
        self.source = source

    def __call__(self, idx: Any) -> torch.Tensor:
        return self.source(idx).double()


@contextmanager
def no_stochastic_depth(net: torch.nn.Module) -> Iterator[None]:
    """Stochastic depth off while inside (its draws would differ between dtypes): the gradients compared are of
    one deterministic function."""
    drops = [(m, m.p) for m in net.modules() if isinstance(m, StochasticDepth)]
    for m, _ in drops:
        m.p = 0.0
    try:
        yield
    finally:
        for m, p in drops:
            m.p = p


def exact_gradients(arch: str, device: torch.device, cache: FrameCache, *, pairs: int, seed: int,
                    backbone: str = PAPER_BACKBONE, frozen: int = 0) -> torch.Tensor:
    """The gradients every candidate's are compared with: the same network, weights and batch in float64."""
    t = _trainer(arch, device, "32", False, cache, pairs=pairs, steps=1, seed=seed, on_step=lambda s, n: None,
                 backbone=backbone, frozen=frozen)
    t.net.double()
    t.source = _Float64Source(t.source)
    with no_stochastic_depth(t.net):
        return batch_gradients(t, 0)[1]


def grad_gap(grads: torch.Tensor | None, reference: torch.Tensor | None) -> float:
    """How far one batch's gradients are from the reference's, from the same weights: ``||g - g_ref|| / ||g_ref||``
    over every trainable parameter at once (inf when missing, of another size or not finite)."""
    if grads is None or reference is None or grads.shape != reference.shape or not grads.numel():
        return math.inf
    g, ref = grads.double(), reference.double()
    gap = float(torch.linalg.vector_norm(g - ref) / torch.linalg.vector_norm(ref).clamp_min(1e-30))
    return gap if math.isfinite(gap) else math.inf


def reference_learns(blocks: Sequence[float]) -> bool:
    """The reference's loss fell enough after its first block (last block <= ``MIN_DROP`` x the second) for a gap
    from it to mean something."""
    return len(blocks) >= 3 and all(map(math.isfinite, blocks)) and blocks[-1] <= MIN_DROP * blocks[1]


def choose(trials: Sequence[Trial], default: tuple[str, bool]) -> Trial:
    """The fastest trial that qualifies (:attr:`Trial.qualifies`), if ``speed.MIN_GAIN`` times faster than
    ``default``'s."""
    base = next(t for t in trials if (t.precision, t.channels_last) == default)
    ok = [t for t in trials if t.qualifies]
    best = max(ok, key=lambda t: t.pairs_per_s, default=base)
    return best if best.pairs_per_s >= speed.MIN_GAIN * base.pairs_per_s else base


def measure_arch(arch: str, device: torch.device, cache: FrameCache, *, pairs: int, steps: int,
                 progress: Callable[[str], None] = lambda text: None, backbone: str = PAPER_BACKBONE,
                 frozen: int = 0) -> dict[str, Any]:
    """Every candidate of ``arch`` on ``device``; the settings-file entry of this architecture."""
    kind = device.type
    default_prec, default_cl = speed.DEFAULTS.get(kind, ("32", True))
    if kind == "cuda" and not bf16_fast(device):
        default_prec = "16-mixed"
    settings: list[tuple] = list(candidates(device))
    if kind == "cuda":  # fp32 trains with TF32 on CUDA (training.device.device_for); the reference is fp32 without it
        settings = [(p, cl, True) for p, cl in settings] + [("32", True, False)]
    progress(f"{arch}: {', '.join(label(*st[:2]) for st in settings[:len(candidates(device))])}"
             f"{' and the fp32 reference (TF32 off)' if kind == 'cuda' else ''}, {steps} steps each, interleaved")
    trials = train_trials(arch, device, settings, cache, pairs=pairs, steps=steps, backbone=backbone, frozen=frozen)
    reference = trials.pop() if kind == "cuda" else trials[0]  # fp32 channels-last: the CPU default
    learns = reference_learns(reference.blocks)
    exact = exact_gradients(arch, device, cache, pairs=pairs, seed=0, backbone=backbone, frozen=frozen)
    for t in trials if any(t is reference for t in trials) else [*trials, reference]:  # each once
        t.grad_error = grad_gap(t.grads, exact)
        t.grads = None
    bound = max(speed.GRAD_TOLERANCE, reference.grad_error)  # as exact as the default, or within the tolerance
    for t in trials:
        t.gap = loss_gap(t.blocks, reference.blocks) if learns or t is reference else math.inf
        t.exact = t.grad_error <= bound
    if (default_prec, default_cl) not in [(t.precision, t.channels_last) for t in trials]:
        default_prec = "32"  # e.g. 16-mixed default on a GPU without bf16: compare with fp32 instead
    chosen = choose(trials, (default_prec, default_cl))
    base = next(t for t in trials if (t.precision, t.channels_last) == (default_prec, default_cl))
    return {
        "precision": chosen.precision, "channels_last": chosen.channels_last, "chosen": chosen.name,
        "default": base.name, "ratio": chosen.pairs_per_s / base.pairs_per_s,
        "pairs_per_s": {t.name: round(t.pairs_per_s, 2) for t in trials}, "reference_learns": learns,
        "loss_gap": {t.name: round(t.gap, 4) if math.isfinite(t.gap) else None for t in trials},
        "grad_error": {t.name: float(f"{t.grad_error:.3g}") if math.isfinite(t.grad_error) else None for t in trials},
        "loss_blocks": {"reference": [round(x, 4) for x in reference.blocks],
                        **{t.name: [round(x, 4) for x in t.blocks] for t in trials}},
    }


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    info = speed.cpu_info()
    model = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")),
                 platform.processor() or platform.machine())
    return f"{model} ({speed.cpu_key(info)}), {torch.get_num_threads()} thread(s)"


def measure(archs: Sequence[str], device: torch.device, *, image_size: int, pairs: int, steps: int,
            progress: Callable[[str], None] = lambda text: None, backbone: str = PAPER_BACKBONE,
            frozen: int = 0) -> tuple[str, dict[str, Any]]:
    """The settings-file entry of ``device``: (its key, the entry) for ``archs`` (``frozen``: trained on a cached
    prefix of that many stages of ``backbone``)."""
    if steps < 5 * BLOCK:
        raise BronchoError(f"--steps {steps}: the numerics check needs at least {5 * BLOCK} steps "
                           f"({BLOCK}-step loss blocks)")
    if pairs < 1:
        raise BronchoError(f"--batch {pairs}: must be at least 1 pair per step")
    if any(ARCHITECTURES[a].temporal for a in archs) and pairs % min(WINDOW, pairs):
        raise BronchoError(f"--batch {pairs}: temporal models need a multiple of {WINDOW} pairs (or fewer)")
    started = time.perf_counter()
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # as training does (training.device.device_for)
    entry: dict[str, Any] = {"archs": {}}
    with tempfile.TemporaryDirectory(prefix="bronchopose-speed-") as tmp:
        cache = synthetic_cache(Path(tmp), frames=max(48, 4 * pairs), size=image_size)
        for arch in archs:
            entry["archs"][arch] = measure_arch(arch, device, cache, pairs=pairs, steps=steps, progress=progress,
                                                backbone=backbone, frozen=frozen)
    entry["measured"] = {
        "date": dt.date.today().isoformat(), "device": _device_name(device), "torch": torch.__version__,
        "threads": torch.get_num_threads(), "image_size": image_size, "pairs_per_step": pairs, "steps": steps,
        "block_steps": BLOCK, "loss_tolerance": speed.LOSS_TOLERANCE, "grad_tolerance": speed.GRAD_TOLERANCE,
        "min_gain": speed.MIN_GAIN,
        "backbone": backbone, "frozen_stages": frozen,
        "seconds": round(time.perf_counter() - started, 1),
    }
    return device_key(device), entry


def markdown(key: str, entry: dict[str, Any]) -> str:
    """The measurement as a Markdown table: pairs/s per candidate, ratios to the default, loss gaps, choice."""
    m = entry["measured"]
    names = list(next(iter(entry["archs"].values()))["pairs_per_s"])
    head = ["arch", *(f"{n} pairs/s" for n in names), *(f"{n} gradient error" for n in names),
            *(f"{n} loss gap" for n in names[1:]), "chosen", "× default"]
    part = speed.frozen_key(m.get("backbone", PAPER_BACKBONE), m.get("frozen_stages", 0))
    lines = [f"Speed settings for `{key}`{f' ({part}: a cached frozen prefix)' if part else ''} "
             f"({m['device']}, torch {m['torch']}, {m['image_size']}², "
             f"{m['pairs_per_step']} pairs/step, {m['steps']} steps, gradient tolerance "
             f"{m.get('grad_tolerance', speed.GRAD_TOLERANCE):.0e}, loss tolerance {m['loss_tolerance']:.0%} per "
             f"{m['block_steps']}-step block, {m['seconds']:.0f} s)", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for arch, a in entry["archs"].items():
        rates = [f"{a['pairs_per_s'][n]:.1f}" for n in names]
        grads = ["—" if a.get("grad_error", {}).get(n) is None else f"{a['grad_error'][n]:.1e}" for n in names]
        gaps = ["—" if a["loss_gap"][n] is None else f"{a['loss_gap'][n]:.1%}" for n in names[1:]]
        flat = (" (the reference did not learn: no loss curve could be checked)"
                if a.get("reference_learns") is False else "")
        lines.append(f"| {arch} | " + " | ".join(rates + grads + gaps) + f" | {a['chosen']}{flat} | {a['ratio']:.2f} |")
    return "\n".join(lines)


def run(archs: Sequence[str], device: torch.device, out: Path, *, image_size: int, pairs: int, steps: int,
        progress: Callable[[str], None] = lambda text: None, backbone: str = PAPER_BACKBONE, frozen: int = 0) -> str:
    """Measure, write ``out`` (this device's entry, or its frozen-prefix entry; the rest kept) and return the
    Markdown table."""
    with exact_fp32():  # restores the TF32 switches the trials set
        key, entry = measure(archs, device, image_size=image_size, pairs=pairs, steps=steps, progress=progress,
                             backbone=backbone, frozen=frozen)
    speed.write(out, key, entry, speed.frozen_key(backbone, frozen))
    return markdown(key, entry)
