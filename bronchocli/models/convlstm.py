"""``convlstm`` (the paper's "ConvRNN", BronchoTrack): a convolutional LSTM over the pair feature maps.

Conv2d 2560->256 3x3 pad 1 + BN + SiLU -> IR(256->128, s2) -> ConvLSTM(128->32,
3x3, 1 layer) over the sequence -> flatten 32·4·4 = 512 -> Linear(512, 6) at every step
(paper: 14.142 M parameters). State: ``(h, c)``, each ``[B, 32, h, w]`` at the map's own
resolution (4x4 at 256x256 input).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .backbones import InvertedResidual
from .base import PAPER_BACKBONE, EfficientPairNet, State, fusion, pool_to

GRID = (4, 4)  # the map after one stride-2 block at 256x256 input
HIDDEN = 32


class ConvLSTMCell(nn.Module):
    """One ConvLSTM step: a single conv over [x, h] gives the input, forget, output and cell gates."""

    def __init__(self, cin: int, hidden: int, kernel: int = 3) -> None:
        super().__init__()
        self.hidden = hidden
        self.conv = nn.Conv2d(cin + hidden, 4 * hidden, kernel, padding=kernel // 2, bias=True)

    def forward(self, x: Tensor, state: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
        h, c = state
        i, f, o, g = self.conv(torch.cat([x, h.to(x.dtype)], dim=1)).chunk(4, dim=1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
        return h, c

    def initial_state(self, x: Tensor) -> tuple[Tensor, Tensor]:
        zeros = x.new_zeros(x.shape[0], self.hidden, *x.shape[-2:])
        return zeros, zeros.clone()


class ConvLSTMNet(EfficientPairNet):
    recurrent = True
    temporal = True

    def __init__(self, image_size: int = 256, dropout: float = 0.2, backbone: str = PAPER_BACKBONE) -> None:
        super().__init__(image_size, dropout, backbone)
        self.fusion = fusion(3, nn.SiLU)
        self.ir = InvertedResidual(256, 128, 2, dropout)
        self.convlstm = ConvLSTMCell(128, HIDDEN, 3)
        self.head = nn.Linear(HIDDEN * GRID[0] * GRID[1], 6)

    def forward(self, frames: Tensor, state: State = None) -> tuple[Tensor, State]:
        b, t = frames.shape[:2]
        x = self.ir(self.fusion(self.pair_features(frames)))
        x = x.view(b, t - 1, *x.shape[1:])
        h, c = state if state is not None else self.convlstm.initial_state(x[:, 0])
        outputs = []
        for step in range(t - 1):
            h, c = self.convlstm(x[:, step], (h, c))
            outputs.append(self.head(pool_to(h, GRID).flatten(1)))
        return torch.stack(outputs, dim=1), (h, c)
