"""``conv3d``: per-pair fusion, then 3-D convolutions over (time, height, width) of the window.

Per pair: Conv2d 2560->256 1x1 *padding 1* + BN + ReLU (the padding grows the map
by one pixel on each side, as in the authors' code) -> stack over time -> two residual
blocks ``x + ReLU(BN3d(Conv3d 256->256 3x3x3 pad 1))`` -> Conv3d 256->256 3x3x3 pad (1, 0, 0)
+ BN3d + ReLU -> AdaptiveAvgPool3d((None, 1, 1)) -> Linear(256, 6) per step (paper:
13.983 M parameters). Temporal padding keeps the length: T-1 pairs in, T-1 poses out.
Not recurrent: each forward sees only its own window.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .backbones import BatchNorm3d
from .base import PAPER_BACKBONE, EfficientPairNet, State, fusion


def _block3d(padding: tuple[int, int, int]) -> nn.Sequential:
    # The Conv3d keeps its bias (as in the authors' code): without it the model
    # would have 13.982 M parameters instead of the paper's 13.983 M.
    return nn.Sequential(nn.Conv3d(256, 256, 3, 1, padding), BatchNorm3d(256), nn.ReLU(inplace=True))


class Conv3dNet(EfficientPairNet):
    recurrent = False
    temporal = True

    def __init__(self, image_size: int = 256, dropout: float = 0.2, backbone: str = PAPER_BACKBONE) -> None:
        super().__init__(image_size, dropout, backbone)
        self.fusion = fusion(1, nn.ReLU, padding=1)
        self.blocks = nn.ModuleList([_block3d((1, 1, 1)) for _ in range(2)])
        self.final = _block3d((1, 0, 0))
        self.pool = nn.AdaptiveAvgPool3d((None, 1, 1))
        self.head = nn.Linear(256, 6)

    def forward(self, frames: Tensor, state: State = None) -> tuple[Tensor, None]:
        b, t = frames.shape[:2]
        x = self.fusion(self.pair_features(frames))  # [B·(T-1), 256, h+2, w+2]
        x = x.view(b, t - 1, *x.shape[1:]).transpose(1, 2)  # [B, 256, T-1, h+2, w+2]
        if self._memory_format is torch.channels_last:
            x = x.contiguous(memory_format=torch.channels_last_3d)
        for block in self.blocks:
            x = block(x) + x
        x = self.pool(self.final(x)).flatten(2).transpose(1, 2)  # [B, T-1, 256]
        return self.head(x), None
