"""Count what a piece of PyTorch code dispatches: operations, dtype casts, views, host syncs.

``OpCounter`` is a ``TorchDispatchMode``: every ATen operation that reaches a
kernel (forward, backward and optimiser alike) passes through it, so the
counts are what a GPU would launch or the host would wait for, measured on the
CPU. A *host sync* is an operation that copies a device value back to Python
(``aten._local_scalar_dense``: ``.item()``, ``float(t)``, ``bool(t)``,
``.tolist()`` of a scalar; on CUDA each one waits for the whole queue).
"""

from __future__ import annotations

from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode

SYNC_OPS = frozenset({"aten._local_scalar_dense", "aten.item"})
CAST_OPS = frozenset({"aten._to_copy", "aten.to", "aten._autocast_to_reduced_precision",
                      "aten._autocast_to_full_precision"})
VIEW_OPS = frozenset({"aten.view", "aten._unsafe_view", "aten.reshape", "aten.t", "aten.transpose",
                      "aten.permute", "aten.expand", "aten.slice", "aten.select", "aten.unsqueeze", "aten.squeeze",
                      "aten.detach", "aten.alias", "aten.as_strided", "aten.split", "aten.chunk",
                      "aten.split_with_sizes", "aten.unbind", "aten.flatten", "aten.unflatten"})
COPY_OPS = frozenset({"aten.clone", "aten.copy_", "aten.contiguous", "aten.empty_like", "aten.zeros_like"})


def _name(func) -> str:
    return f"{func.namespace}.{func._schema.name.split('::')[-1]}" if hasattr(func, "namespace") else str(func)


class OpCounter(TorchDispatchMode):
    """``with OpCounter() as c: ...`` then ``c.total``, ``c.syncs``, ``c.casts``, ``c.views``, ``c.by_name``."""

    def __init__(self) -> None:
        super().__init__()
        self.by_name: Counter[str] = Counter()
        self.dtypes: Counter[torch.dtype] = Counter()  # dtypes of floating-point outputs

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        self.by_name[_name(func.overloadpacket)] += 1
        for t in out if isinstance(out, (tuple, list)) else (out,):
            if isinstance(t, torch.Tensor) and t.is_floating_point():
                self.dtypes[t.dtype] += 1
        return out

    def _count(self, names: frozenset[str]) -> int:
        return sum(n for k, n in self.by_name.items() if k in names)

    @property
    def total(self) -> int:
        return sum(self.by_name.values())

    @property
    def syncs(self) -> int:
        return self._count(SYNC_OPS)

    @property
    def casts(self) -> int:
        return self._count(CAST_OPS)

    @property
    def views(self) -> int:
        return self._count(VIEW_OPS)

    @property
    def copies(self) -> int:
        return self._count(COPY_OPS)

    def summary(self) -> dict[str, int]:
        return {"ops": self.total, "casts": self.casts, "views": self.views, "copies": self.copies,
                "syncs": self.syncs}


def count_step(trainer, steps: int = 1) -> OpCounter:
    """Operations dispatched by ``steps`` optimiser steps of ``trainer`` (``training.loop.Trainer``), after one
    warm-up step (lazy optimiser state, the first batch's one-off work), with the validation outside and the
    non-finite check at its CUDA interval."""
    trainer.check_every = max(trainer.check_every, 25)  # the non-finite check at its CUDA interval
    trainer._train_until(trainer.step + 1)
    with OpCounter() as counter:
        trainer._train_until(trainer.step + steps)
    return counter
