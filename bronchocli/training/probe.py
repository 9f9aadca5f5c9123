"""One batch's loss and gradients from a trainer's current weights, without training: what ``profile --speed``
compares between settings (two memory formats of fp32 compute one function; diagnostics/speed.py).

It runs the trainer's own chunked forward and backward (``Trainer._backward_chunks``: the same autocast, chunks,
loss and scaler as a training step) and then puts everything back: the network's weights and BatchNorm statistics,
the optimiser's gradients, the loss counters and the random generators (stochastic depth draws from them).
"""

from __future__ import annotations

import torch

from .loop import Trainer


def batch_gradients(trainer: Trainer, i: int = 0) -> tuple[float, torch.Tensor]:
    """The training loss of sample batch ``i`` (mean over its chunks) and the gradient of its chunks' summed losses
    for every trainable parameter (flattened in parameter order, logical element order whatever the memory format;
    unscaled); the trainer is left as it was."""
    t = trainer
    saved = {k: v.clone() for k, v in t.net.state_dict().items()}
    loss_sum, loss_n, was = t._loss_sum.clone(), t._loss_n, t.net.training
    with torch.random.fork_rng(devices=[t.device] if t.device.type == "cuda" else []):
        t.net.train()
        t.opt.zero_grad(set_to_none=True)
        try:
            for _ in t._backward_chunks(*t._batch(i)):
                pass
            loss = float((t._loss_sum - loss_sum) / max(t._loss_n - loss_n, 1))
            undo = t.s.accum / (t.scaler.get_scale() if t.scaler.is_enabled() else 1.0)
            grads = [p.grad.detach().float().flatten() for p in t.net.parameters() if p.grad is not None]
            return loss, torch.cat(grads).cpu() * undo if grads else torch.zeros(0)
        finally:
            t.opt.zero_grad(set_to_none=True)
            t.net.load_state_dict(saved)
            t._loss_sum.copy_(loss_sum)
            t._loss_n = loss_n
            t.net.train(was)
