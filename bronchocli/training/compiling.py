"""``torch.compile`` of the network for training (``train.compile``)."""

from __future__ import annotations

import torch
from torch import nn

from ..errors import BronchoError

COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


def compile_network(net: nn.Module, mode: bool | str, backend: str | None = None) -> nn.Module:
    """``net`` compiled by ``torch.compile`` in ``mode`` (True: ``default``; False: ``net`` itself).

    ``reduce-overhead`` replays the compiled forward and backward as CUDA graphs (one launch per graph
    instead of one per operation: what a launch-bound step needs; shapes are fixed and the step makes no
    host sync, so capture holds). ``backend`` (tests): a backend that needs no code generation, e.g.
    ``eager`` or ``aot_eager``, in which case the mode (an inductor option) does not apply.
    """
    if mode is False or mode is None:
        return net
    mode = "default" if mode is True else mode
    if mode not in COMPILE_MODES:
        raise BronchoError(f"train.compile {mode!r}: must be false, true or one of {', '.join(COMPILE_MODES)}")
    if backend is not None:
        return torch.compile(net, backend=backend)
    return torch.compile(net, mode=mode)
