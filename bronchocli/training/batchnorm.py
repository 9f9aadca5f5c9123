"""BatchNorm between training and evaluation: re-estimated statistics, the mode gap, and the freeze that closes it.

Training normalises each BatchNorm with the statistics of the batch at hand; evaluation with population
(running) statistics. At 64² the EfficientNet-B0 backbone's last stages run on 2×2 maps and the ShuffleNet head
on 1×1, so a batch of 20 pairs gives a BatchNorm of the head 20 values per channel: the per-batch statistics are
part of the function the network learns, and population statistics — however well re-estimated — give another
function (issue 35: eval-mode loss 1.5–3× the train-mode loss on the same training batches).

* :func:`recalibrate_bn` re-estimates the running statistics as a plain average over training batches.
* :func:`mode_gap` measures the disagreement: eval-mode loss ÷ batch-statistics loss on the same training
  batches, dropout and stochastic depth off in both (logged as ``val.mode_gap`` per validation and
  ``eval.mode_gap`` for the tested weights).
* :func:`freeze_bn` puts every BatchNorm in eval mode while the rest trains: the last ``train.bn_freeze`` of the
  steps train the very function that is evaluated (statistics re-estimated once when the freeze starts, then
  fixed; the affine weights keep learning). The model stays the paper's: the same modules and state-dict keys.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

import torch
from torch import nn

GAP_AT_MOST = 1.10  # the largest mode gap the memorisation self-test accepts (diagnostics/learning.py)


def batchnorms(net: nn.Module) -> list[nn.modules.batchnorm._BatchNorm]:
    """The BatchNorms training normalises with batch statistics: every one but those of frozen backbone stages
    (``model.frozen_stages``: they keep the statistics they were initialised with, in eval mode throughout)."""
    return [m for m in net.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)
            and not getattr(m, "frozen", False)]


@torch.no_grad()
def recalibrate_bn(net: nn.Module, batches: Iterator[torch.Tensor], autocast, *, biased: bool = False) -> int:
    """Re-estimate every BatchNorm's running statistics as the plain average over ``batches``.

    Dropout and stochastic depth are off while the statistics are measured: evaluation runs without them, and
    statistics measured with them describe another distribution (dropout's variance shift; stochastic depth
    drops whole residual branches). Measured with them on, the baseline at 32² memorised 28 pairs to 0.15 × the
    mean predictor's loss in eval mode against 0.03 with batch statistics (a mode gap of 5).

    The average is built with an explicit momentum of ``1 / (k + 1)`` for batch ``k`` (``r <- (1 - m) r + m x``
    gives the running mean of the ``k + 1`` batch statistics), computed on the host from a counter kept here:
    PyTorch's own cumulative mode (``momentum=None``) reads ``num_batches_tracked`` back from the device in
    every BatchNorm of every batch (a host sync each: 1,744 per validation for the baseline on CUDA).

    The running variance is PyTorch's unbiased one (× m / (m - 1), m values per channel and batch): the
    population's. ``biased``: the plain average of the batch variances training normalised with instead — what
    evaluation on the very batches it was measured on must use to reproduce them (at 1×1 maps and 28 pairs the
    factor alone made eval-mode loss 1.43× the batch-statistics loss of a memorised set).
    """
    bns = batchnorms(net)
    if not bns:
        return 0
    momenta = [m.momentum for m in bns]
    for m in bns:
        m.reset_running_stats()
    was_training = net.training
    net.eval()  # dropout and stochastic depth off: the statistics of the network that is evaluated ...
    for m in bns:
        m.train()  # ... each BatchNorm measuring its batch
    n = 0
    counts: dict[int, int] = {}  # values per channel and batch, for ``biased``

    def count(m: nn.Module, args: tuple[torch.Tensor, ...]) -> None:
        counts.setdefault(id(m), args[0].numel() // args[0].shape[1])

    hooks = [m.register_forward_pre_hook(count) for m in bns] if biased else []
    try:
        for frames in batches:
            for m in bns:
                m.momentum = 1.0 / (n + 1)
            with autocast():
                net(frames)
            n += 1
    finally:
        for h in hooks:
            h.remove()
        for m, mom in zip(bns, momenta):
            m.momentum = mom
        net.train(was_training)
    for m in bns:
        if biased and counts.get(id(m), 0) > 1:
            m.running_var.mul_((counts[id(m)] - 1) / counts[id(m)])
    return n


def freeze_bn(net: nn.Module) -> int:
    """Every BatchNorm of ``net`` to eval mode (population statistics, not updated); the rest keeps its mode.
    Call after each ``net.train()``. Returns how many were frozen."""
    bns = batchnorms(net)
    for m in bns:
        m.eval()
    return len(bns)


@contextmanager
def batch_statistics(net: nn.Module) -> Iterator[None]:
    """``net`` in eval mode except its BatchNorms, which normalise with the batch's statistics (as in training)
    without touching their running statistics or counters. Dropout and stochastic depth stay off."""
    bns = batchnorms(net)
    was_training = net.training
    saved = [(m.momentum, None if m.num_batches_tracked is None else m.num_batches_tracked.clone()) for m in bns]
    net.eval()
    for m in bns:
        m.train()
        m.momentum = 0.0  # r <- (1 - 0) r + 0 x: the running statistics stay as they are
    try:
        yield
    finally:
        for m, (mom, count) in zip(bns, saved):
            m.momentum = mom
            if count is not None:
                m.num_batches_tracked.copy_(count)
        net.train(was_training)


@torch.no_grad()
def mode_gap(net: nn.Module, batches: Iterable[tuple[torch.Tensor, torch.Tensor]],
             loss: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], autocast) -> dict[str, float]:
    """Eval-mode loss, batch-statistics loss and their ratio (the mode gap) on the same training ``batches``.

    ``batches`` holds (frames, labels) pairs of training batches as the loop draws them; ``loss(out, labels)`` is
    the training loss. 1.0: evaluation computes what training optimised; above 1: evaluation is worse.
    """
    was_training = net.training
    totals = {"eval": [], "batch": []}
    batches = list(batches)
    try:
        net.eval()
        for frames, labels in batches:
            with autocast():
                out, _ = net(frames)
            totals["eval"].append(loss(out.float(), labels))
        with batch_statistics(net):
            for frames, labels in batches:
                with autocast():
                    out, _ = net(frames)
                totals["batch"].append(loss(out.float(), labels))
    finally:
        net.train(was_training)
    ev, bs = torch.stack([torch.stack(totals["eval"]).mean(), torch.stack(totals["batch"]).mean()]).tolist()
    return {"mode_gap": ev / bs if bs > 0 else float("inf"), "mode_gap.eval_loss": ev, "mode_gap.batch_loss": bs}
