"""Can this architecture learn on this data? ``bronchopose selftest --learn``: two checks in a minute or two.

Both run the platform's own path (prepare -> network -> Trainer) on a handful of the configured dataset's
training samples (``pairs`` image pairs, evenly spread, the same every time), trained as one full batch:

1. **overfit** — ``steps`` optimiser steps on those samples alone; then, BatchNorm re-estimated on them as
   every validation does, their eval-mode loss must fall below ``OVERFIT_BELOW`` × the loss of the
   training-mean predictor on the same samples (their own statistics: the plain average of the batch
   variances every step normalised with, not PyTorch's unbiased population estimate). A model that cannot memorise 30 pairs cannot learn from 3,000:
   a failure points at the labels, the pairing, the normalisation or the loss, not at the budget.
2. **consistency** — eval-mode loss ÷ batch-statistics loss on those samples (``mode_gap``,
   training/batchnorm.py) at most ``GAP_AT_MOST``. With the whole set in every batch the batch statistics are
   the set's own, so a larger gap means that re-estimated statistics (measured in eval mode: dropout and
   stochastic depth off) do not reproduce what training computed (memorising smaller batches of a handful of samples instead teaches the network their
   batch statistics: a gap of 1.9 for ConvLSTM, which says nothing about the full data; the runs' own
   ``val.mode_gap`` measures that).

Passing both says the model *can* learn here; whether it generalises at a budget is what a sweep measures
against the image-blind references (benchmarks/README.md, "Learning from scratch").
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from ..cells import Cell
from ..config import Config
from ..data.batches import FrameSource
from ..training.batchnorm import GAP_AT_MOST, mode_gap, recalibrate_bn
from ..training.device import device_for, seed_everything
from ..training.engine import build_network, settings
from ..training.loop import Trainer
from ..training.prepare import prepare

OVERFIT_BELOW = 0.3  # eval-mode loss on the memorised samples ÷ the training-mean predictor's
PAIRS = 30  # image pairs memorised, one full batch (pairwise: 30 pairs; temporal: 3 windows of 10)
STEPS = 100


@dataclass(frozen=True)
class Verdict:
    arch: str
    pairs: int
    steps: int
    overfit: float  # eval-mode loss ÷ the training-mean predictor's on the memorised samples
    gap: float
    seconds: float

    @property
    def learns(self) -> bool:
        return self.overfit <= OVERFIT_BELOW

    @property
    def consistent(self) -> bool:
        return self.gap <= GAP_AT_MOST

    @property
    def ok(self) -> bool:
        return self.learns and self.consistent and math.isfinite(self.overfit)

    def line(self) -> str:
        head = f"{self.arch} can learn here" if self.ok else f"{self.arch} cannot be shown to learn here"
        fit = (f"memorised {self.pairs} training pairs to {self.overfit:.3f} x the training-mean predictor's loss "
               f"in {self.steps} steps (needs <= {OVERFIT_BELOW})")
        gap = f"eval/train-mode gap {self.gap:.3f} (needs <= {GAP_AT_MOST})"
        return f"{head}: {fit}; {gap}; {self.seconds:.0f} s"


def check(cfg: Config, cell: Cell, *, pairs: int = PAIRS, steps: int = STEPS) -> Verdict:
    """Run both checks for ``cell``'s architecture on ``cfg``'s dataset (which must exist)."""
    t0 = time.perf_counter()
    device = device_for(cfg)
    data = prepare(cfg, cell, progress=False)
    per_sample = data.train.n_pairs
    subset = data.train.evenly(max(pairs, per_sample))
    seed_everything(cell.seed)
    net = build_network(cfg, cell, data, device)
    micro = len(subset) * per_sample  # one full batch: the batch statistics are the set's own
    s = settings(cfg, cell, device)
    s = s.__class__(**{**s.__dict__, "steps": steps, "micro_pairs": micro, "accum": 1, "val_every": steps,
                       "patience": None, "bn_recalibrate": 1, "bn_freeze": 0.0, "mode_gap_batches": 0,
                       "augment": False, "checkpoint_every_s": math.inf, "log_every": 0})
    trainer = Trainer(net, subset, subset, FrameSource(data.cache, device, cfg.data.frames_on_device), s,
                      device=device)
    fit = trainer.fit()
    frames, labels = trainer._batch(0)  # the whole set, as every step saw it
    recalibrate_bn(net, iter([frames]), trainer.autocast, biased=True)  # its own statistics, as trained
    gap = mode_gap(net, [(frames, labels)], lambda out, y: net.loss(out, y, s.rot_loss, s.rot_weight, s.rot_scale),
                   trainer.autocast)
    mean = torch.from_numpy(data.label_mean.astype("float32")).to(device)
    reference = float(net.loss(mean.expand_as(labels), labels, s.rot_loss, s.rot_weight, s.rot_scale))
    overfit = gap["mode_gap.eval_loss"] / reference if reference > 0 else math.inf
    return Verdict(cell.arch, len(subset) * per_sample, fit.steps, overfit, gap["mode_gap"],
                   time.perf_counter() - t0)
