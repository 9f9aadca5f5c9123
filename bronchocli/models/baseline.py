"""``baseline``: two EfficientNet-B0 backbones, a fusion conv and two ShuffleNet blocks; pairs independent.

Layers after the 2560-channel pair features (paper, 13.967 M parameters at 256x256):
Conv2d 2560->256 3x3 pad 1 + BN + ReLU -> IR(256->128, s2) -> IR(128->64, s2)
-> flatten 64·2·2 = 256 -> Linear(256, 6).
"""

from __future__ import annotations

from torch import Tensor, nn

from .backbones import InvertedResidual
from .base import PAPER_BACKBONE, EfficientPairNet, State, fusion, pool_to

GRID = (2, 2)  # the map after the two stride-2 blocks at 256x256 input


class BaselineNet(EfficientPairNet):
    recurrent = False
    temporal = False

    def __init__(self, image_size: int = 256, dropout: float = 0.2, backbone: str = PAPER_BACKBONE) -> None:
        super().__init__(image_size, dropout, backbone)
        self.fusion = fusion(3, nn.ReLU)
        self.ir = nn.Sequential(InvertedResidual(256, 128, 2, dropout), InvertedResidual(128, 64, 2, dropout))
        self.head = nn.Linear(64 * GRID[0] * GRID[1], 6)

    def forward(self, frames: Tensor, state: State = None) -> tuple[Tensor, None]:
        b, t = frames.shape[:2]
        x = pool_to(self.ir(self.fusion(self.pair_features(frames))), GRID)
        return self.head(x.flatten(1)).view(b, t - 1, 6), None
