"""``offsetnet``: the state-of-the-art comparison (Sganga et al. 2019), as the BronchoPose authors ran it.

Two separate ResNet-34 (torchvision layout, each with its 1000-way ``fc``), current frame
first -> concatenate 2000 -> Linear(2000, 6) (43.6 M parameters). Pairs are independent.
It has no ShuffleNet blocks, so ``dropout`` does not apply.
"""

from __future__ import annotations

from torch import Tensor, nn

from .backbones import ResNet34
from .base import PoseNet, State


class OffsetNet(PoseNet):
    recurrent = False
    temporal = False
    backbone_kind = "resnet34"

    def __init__(self, image_size: int = 256, dropout: float = 0.2) -> None:
        super().__init__(image_size, dropout)
        self.backbone_cur = ResNet34()
        self.backbone_prev = ResNet34()
        self.head = nn.Linear(2 * ResNet34.out_features, 6)

    def forward(self, frames: Tensor, state: State = None) -> tuple[Tensor, None]:
        b, t = frames.shape[:2]
        return self.head(self.pair_features(frames)).view(b, t - 1, 6), None
