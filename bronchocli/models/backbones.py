"""Backbones written in the project, with torchvision's parameter names so its checkpoints load.

torchvision cannot be imported next to the CPU torch build used here, so the
three building blocks the architectures need are defined in this module,
layer for layer as in torchvision (``efficientnet.py``, ``resnet.py``,
``shufflenetv2.py``), so that the state-dict keys and shapes are identical:

* ``EfficientNetB0Features``: ``efficientnet_b0().features`` (all nine stages,
  1280 channels, stride 32), 4,007,548 parameters. Its keys are
  ``features.0.0.weight``, ``features.1.0.block.0.0.weight``, ... exactly as in
  a torchvision ``efficientnet_b0`` state dict (whose ``classifier.*`` keys are
  simply not used). Stochastic depth (row mode, linearly rising to 0.2) and the
  weight initialisation are torchvision's too.
* ``ResNet34``: torchvision's ``resnet34`` including its 1000-way ``fc``
  (21,797,672 parameters): keys ``conv1.weight``, ``layer1.0.conv1.weight``,
  ..., ``fc.weight``.
* ``InvertedResidual``: ShuffleNetV2's block (``branch1``/``branch2`` plus a
  channel shuffle) with one addition the BronchoPose paper asks for: a dropout
  layer at the end of each branch, after its last ReLU and before the
  concatenation and shuffle. Dropout has no parameters, so the keys stay
  torchvision's.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# torchvision's efficientnet_b0 stages: (expand ratio, kernel, stride, in, out, layers).
_B0_STAGES = (
    (1, 3, 1, 32, 16, 1),
    (6, 3, 2, 16, 24, 2),
    (6, 5, 2, 24, 40, 2),
    (6, 3, 2, 40, 80, 3),
    (6, 5, 1, 80, 112, 3),
    (6, 5, 2, 112, 192, 4),
    (6, 3, 1, 192, 320, 1),
)


def _make_divisible(v: float, divisor: int = 8) -> int:
    """Round channels to a multiple of ``divisor`` (torchvision's ``_make_divisible``)."""
    new_v = max(divisor, int(v + divisor / 2) // divisor * divisor)
    return new_v + divisor if new_v < 0.9 * v else new_v


# -- BatchNorm without the batch counter --------------------------------------------


class _Uncounted:
    """A BatchNorm that does not increment ``num_batches_tracked`` in training (one device op per layer per
    forward: 109 of an EfficientNet pair model's ~1,100). The counter only serves PyTorch's cumulative mode
    (``momentum=None``), which this project never uses (``training.loop.recalibrate_bn`` passes explicit
    momenta); with ``momentum=None`` the layer behaves as PyTorch's. Keys and shapes are unchanged, so
    torchvision checkpoints load; the counter stays at what it was loaded with."""

    def forward(self, x: Tensor) -> Tensor:
        if self.momentum is None or not (self.training and self.track_running_stats):
            return super().forward(x)
        self._check_input_dim(x)
        return F.batch_norm(x, self.running_mean, self.running_var, self.weight, self.bias, True, self.momentum,
                            self.eps)


class BatchNorm2d(_Uncounted, nn.BatchNorm2d):
    pass


class BatchNorm3d(_Uncounted, nn.BatchNorm3d):
    pass


# -- EfficientNet-B0 ------------------------------------------------------------


class ConvBNAct(nn.Sequential):
    """Conv2d (no bias) + BatchNorm2d [+ SiLU], named ``0``/``1``/``2`` like torchvision's Conv2dNormActivation."""

    def __init__(self, cin: int, cout: int, kernel: int, stride: int = 1, groups: int = 1, act: bool = True) -> None:
        layers: list[nn.Module] = [
            nn.Conv2d(cin, cout, kernel, stride, (kernel - 1) // 2, groups=groups, bias=False),
            BatchNorm2d(cout),
        ]
        if act:
            # Out of place (torchvision: in place): SiLU's backward needs its input, so an in-place SiLU makes
            # autograd clone the BatchNorm output first: 66 extra copies per forward of the two backbones.
            layers.append(nn.SiLU())
        super().__init__(*layers)


class SqueezeExcitation(nn.Module):
    """Channel attention with 1x1 convs ``fc1``/``fc2`` (torchvision.ops.SqueezeExcitation, SiLU inside)."""

    def __init__(self, channels: int, squeeze: int) -> None:
        super().__init__()
        self.fc1 = nn.Conv2d(channels, squeeze, 1)
        self.fc2 = nn.Conv2d(squeeze, channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        # A plain mean (adaptive_avg_pool2d(x, 1) dispatches 3 operations forward and 4 backward per block)
        scale = self.fc2(F.silu(self.fc1(x.mean((2, 3), keepdim=True))))
        return x * torch.sigmoid(scale)


class StochasticDepth(nn.Module):
    """Drop a whole residual branch per sample while training ("row" mode of torchvision.ops)."""

    def __init__(self, p: float) -> None:
        super().__init__()
        self.p = p

    def forward(self, x: Tensor) -> Tensor:
        if not self.training or self.p == 0.0:
            return x
        keep = 1.0 - self.p
        noise = torch.empty((x.shape[0],) + (1,) * (x.ndim - 1), dtype=x.dtype, device=x.device)
        return x * noise.bernoulli_(keep).div_(keep)

    def extra_repr(self) -> str:
        return f"p={self.p}"


class MBConv(nn.Module):
    """EfficientNet's mobile inverted bottleneck: [expand] -> depthwise -> SE -> project (+ residual)."""

    def __init__(self, expand: int, kernel: int, stride: int, cin: int, cout: int, drop: float) -> None:
        super().__init__()
        self.use_res = stride == 1 and cin == cout
        hidden = _make_divisible(cin * expand)
        layers: list[nn.Module] = []
        if hidden != cin:
            layers.append(ConvBNAct(cin, hidden, 1))
        layers += [
            ConvBNAct(hidden, hidden, kernel, stride, groups=hidden),
            SqueezeExcitation(hidden, max(1, cin // 4)),
            ConvBNAct(hidden, cout, 1, act=False),
        ]
        self.block = nn.Sequential(*layers)
        self.stochastic_depth = StochasticDepth(drop)

    def forward(self, x: Tensor) -> Tensor:
        out = self.block(x)
        return self.stochastic_depth(out) + x if self.use_res else out


class EfficientNetB0Features(nn.Module):
    """``torchvision.models.efficientnet_b0().features``: [B, 3, H, W] -> [B, 1280, H/32, W/32]."""

    out_channels = 1280

    def __init__(self, stochastic_depth: float = 0.2) -> None:
        super().__init__()
        layers: list[nn.Module] = [ConvBNAct(3, 32, 3, stride=2)]
        total = sum(s[-1] for s in _B0_STAGES)
        block_id = 0
        for expand, kernel, stride, cin, cout, n in _B0_STAGES:
            stage = []
            for i in range(n):
                drop = stochastic_depth * block_id / total
                stage.append(MBConv(expand, kernel, stride if i == 0 else 1, cin if i == 0 else cout, cout, drop))
                block_id += 1
            layers.append(nn.Sequential(*stage))
        layers.append(ConvBNAct(320, 1280, 1))
        self.features = nn.Sequential(*layers)
        _init_efficientnet(self)

    def forward(self, x: Tensor) -> Tensor:
        return self.features(x)

    def stages(self) -> list[list[nn.Module]]:
        """The nine stages in input order (stem, seven MBConv stages, head): what ``model.frozen_stages`` counts."""
        return [[m] for m in self.features]

    def run_stages(self, x: Tensor, start: int = 0, stop: int = 9) -> Tensor:
        """Stages ``start`` to ``stop - 1`` only: the input of stage ``start`` -> the output of stage ``stop - 1``."""
        return self.features[start:stop](x)


def _init_efficientnet(module: nn.Module) -> None:
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


# -- ResNet-34 ------------------------------------------------------------------


class BasicBlock(nn.Module):
    """ResNet basic block: two 3x3 convs with BN, identity or 1x1 ``downsample`` shortcut."""

    def __init__(self, cin: int, planes: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, planes, 3, stride, 1, bias=False)
        self.bn1 = BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
        self.bn2 = BatchNorm2d(planes)
        self.downsample: nn.Module | None = None
        if stride != 1 or cin != planes:
            self.downsample = nn.Sequential(nn.Conv2d(cin, planes, 1, stride, bias=False), BatchNorm2d(planes))

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet34(nn.Module):
    """``torchvision.models.resnet34()`` with its 1000-way ``fc``: [B, 3, H, W] -> [B, 1000]."""

    out_features = 1000

    def __init__(self, num_classes: int = 1000) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        cin = 64
        for i, (planes, blocks) in enumerate(((64, 3), (128, 4), (256, 6), (512, 3)), start=1):
            stride = 1 if i == 1 else 2
            layer = [BasicBlock(cin, planes, stride)] + [BasicBlock(planes, planes) for _ in range(blocks - 1)]
            setattr(self, f"layer{i}", nn.Sequential(*layer))
            cin = planes
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.fc = nn.Linear(512, num_classes)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: Tensor) -> Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return self.fc(torch.flatten(self.avgpool(x), 1))


# -- ShuffleNetV2 inverted residual ----------------------------------------------


def channel_shuffle(x: Tensor, groups: int) -> Tensor:
    """Interleave the channels of ``groups`` groups (ShuffleNet): [a0 a1 .. b0 b1 ..] -> [a0 b0 a1 b1 ..]."""
    b, c, h, w = x.shape
    return x.view(b, groups, c // groups, h, w).transpose(1, 2).reshape(b, c, h, w)


def _depthwise(channels: int, stride: int) -> nn.Conv2d:
    return nn.Conv2d(channels, channels, 3, stride, 1, groups=channels, bias=False)


class InvertedResidual(nn.Module):
    """ShuffleNetV2 block (torchvision names) with ``dropout`` at the end of each branch.

    Stride 2: both branches see the whole input and each produces ``oup // 2``
    channels. Stride 1: the input is split in halves, the first half passes
    unchanged (no dropout) and ``branch2`` transforms the second. The outputs
    are concatenated and channel-shuffled with 2 groups.
    """

    def __init__(self, inp: int, oup: int, stride: int, dropout: float = 0.0) -> None:
        super().__init__()
        if stride not in (1, 2, 3):
            raise ValueError(f"InvertedResidual stride must be 1, 2 or 3, got {stride}")
        half = oup // 2
        if stride == 1 and inp != 2 * half:
            raise ValueError(f"InvertedResidual with stride 1 needs inp == oup, got {inp} -> {oup}")
        self.stride = stride
        if stride > 1:
            self.branch1 = nn.Sequential(
                _depthwise(inp, stride),
                BatchNorm2d(inp),
                nn.Conv2d(inp, half, 1, bias=False),
                BatchNorm2d(half),
                nn.ReLU(inplace=True),
                nn.Dropout(dropout),
            )
        else:
            self.branch1 = nn.Sequential()
        self.branch2 = nn.Sequential(
            nn.Conv2d(inp if stride > 1 else half, half, 1, bias=False),
            BatchNorm2d(half),
            nn.ReLU(inplace=True),
            _depthwise(half, stride),
            BatchNorm2d(half),
            nn.Conv2d(half, half, 1, bias=False),
            BatchNorm2d(half),
            nn.ReLU(inplace=True),
            nn.Dropout(dropout),
        )

    def forward(self, x: Tensor) -> Tensor:
        if self.stride == 1:
            x1, x2 = x.chunk(2, dim=1)
            out = torch.cat((x1, self.branch2(x2)), dim=1)
        else:
            out = torch.cat((self.branch1(x), self.branch2(x)), dim=1)
        return channel_shuffle(out, 2)


def n_params(module: nn.Module) -> int:
    """Number of trainable and frozen parameters (buffers such as BN statistics excluded)."""
    return sum(p.numel() for p in module.parameters())

