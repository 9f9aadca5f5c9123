"""``lstm``: the baseline's feature path (with SiLU) feeding an LSTM over the sequence of pairs.

Conv2d 2560->256 3x3 pad 1 + BN + SiLU -> IR(256->128, s2) -> IR(128->64, s2)
-> flatten 256 -> LSTM(256, hidden 128, 1 layer) -> Linear(128, 6) at every step
(paper: 14.164 M parameters). State: ``(h, c)``, each ``[1, B, 128]``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .backbones import InvertedResidual
from .base import PAPER_BACKBONE, EfficientPairNet, State, fusion, pool_to

GRID = (2, 2)


class LSTMNet(EfficientPairNet):
    recurrent = True
    temporal = True

    def __init__(self, image_size: int = 256, dropout: float = 0.2, backbone: str = PAPER_BACKBONE) -> None:
        super().__init__(image_size, dropout, backbone)
        self.fusion = fusion(3, nn.SiLU)
        self.ir = nn.Sequential(InvertedResidual(256, 128, 2, dropout), InvertedResidual(128, 64, 2, dropout))
        self.lstm = nn.LSTM(64 * GRID[0] * GRID[1], 128, num_layers=1, batch_first=True)
        self.head = nn.Linear(128, 6)

    def forward(self, frames: Tensor, state: State = None) -> tuple[Tensor, State]:
        b, t = frames.shape[:2]
        x = pool_to(self.ir(self.fusion(self.pair_features(frames))), GRID)
        # The LSTM runs in fp32 with autocast off: under bf16 autocast PyTorch's cuDNN LSTM path casts to fp16
        # (its autocast policy is fp16-only), so the recurrence would train in fp16 with no loss scaling. It is
        # 0.2 M of the 14 M parameters and a few hundred FLOPs per pair: fp32 costs nothing measurable.
        dtype = self.lstm.weight_ih_l0.dtype  # the weights' own (fp32 in training; fp64 in the exactness tests)
        with torch.autocast(x.device.type, enabled=False):
            seq, (h, c) = self.lstm(x.flatten(1).view(b, t - 1, -1).to(dtype), _cast(state, dtype))
        return self.head(seq), (h, c)


def _cast(state: State, dtype: torch.dtype) -> State:
    return None if state is None else tuple(s.to(dtype) for s in state)
