"""Backbones: torchvision state-dict compatibility (keys, shapes, counts), channel shuffle, dropout sites.

``torchvision_keys.json`` lists every state-dict key and shape of torchvision's
``efficientnet_b0()`` and ``resnet34()``. It was written by transcribing
torchvision's construction code (the ``efficientnet_b0`` MBConv table with
``_make_divisible``, SqueezeExcitation's ``fc1``/``fc2``, Conv2dNormActivation's
``0``/``1`` numbering; ``resnet34``'s [3, 4, 6, 3] BasicBlocks with
``downsample.0``/``.1``) into a key enumerator that does not use this package,
and it reproduces torchvision's published parameter counts (5,288,548 and
21,797,672), which the tests below check again.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from bronchocli.models.backbones import (
    EfficientNetB0Features,
    InvertedResidual,
    ResNet34,
    channel_shuffle,
    n_params,
)

KEYS = json.loads((Path(__file__).parent / "torchvision_keys.json").read_text())
BUFFERS = ("running_mean", "running_var", "num_batches_tracked")


def _param_count(entries: dict[str, list[int]]) -> int:
    return sum(math.prod(shape) for key, shape in entries.items() if not key.endswith(BUFFERS))


def _shapes(module: torch.nn.Module) -> dict[str, list[int]]:
    return {k: list(v.shape) for k, v in module.state_dict().items()}


def test_reference_lists_match_torchvision_published_counts():
    assert _param_count(KEYS["efficientnet_b0"]) == 5_288_548
    assert _param_count(KEYS["resnet34"]) == 21_797_672


def test_efficientnet_b0_features_keys_and_shapes_are_torchvision():
    features = {k: s for k, s in KEYS["efficientnet_b0"].items() if k.startswith("features.")}
    ours = _shapes(EfficientNetB0Features())
    assert list(ours) == list(features)  # same names in the same order
    assert ours == features
    assert n_params(EfficientNetB0Features()) == 4_007_548 == _param_count(features)
    # The only torchvision keys we do not have are the classifier's Linear(1280, 1000).
    assert set(KEYS["efficientnet_b0"]) - set(ours) == {"classifier.1.weight", "classifier.1.bias"}


def test_resnet34_keys_and_shapes_are_torchvision():
    ours = _shapes(ResNet34())
    assert list(ours) == list(KEYS["resnet34"])
    assert ours == KEYS["resnet34"]
    assert n_params(ResNet34()) == 21_797_672


@pytest.mark.parametrize("size", [64, 96, 256])
def test_efficientnet_output_is_1280_channels_at_stride_32(size):
    with torch.no_grad():
        out = EfficientNetB0Features().eval()(torch.randn(1, 3, size, size))
    assert out.shape == (1, 1280, math.ceil(size / 32), math.ceil(size / 32))  # 8x8 at 256


def test_resnet34_output_is_1000_logits():
    with torch.no_grad():
        assert ResNet34().eval()(torch.randn(2, 3, 64, 64)).shape == (2, 1000)


def test_channel_shuffle_interleaves_two_groups():
    x = torch.arange(6.0).view(1, 6, 1, 1)  # groups [0 1 2] and [3 4 5]
    assert channel_shuffle(x, 2).flatten().tolist() == [0, 3, 1, 4, 2, 5]


def test_inverted_residual_has_torchvision_names_and_counts():
    block = InvertedResidual(256, 128, 2, dropout=0.3)
    names = [k for k in block.state_dict() if not k.endswith(BUFFERS)]
    assert names[:2] == ["branch1.0.weight", "branch1.1.weight"]
    assert "branch2.5.weight" in names and "branch2.7.weight" not in names  # 7 is a ReLU, 8 the dropout
    # dw 3x3 256 + BN 256 + 1x1 256->64 + BN 64 | 1x1 256->64 + BN + dw 3x3 64 + BN + 1x1 64->64 + BN
    assert n_params(block) == (2304 + 512 + 16384 + 128) + (16384 + 128 + 576 + 128 + 4096 + 128)
    assert InvertedResidual(256, 128, 2, dropout=0.0).state_dict().keys() == block.state_dict().keys()


def test_inverted_residual_dropout_sits_at_the_end_of_each_branch():
    block = InvertedResidual(8, 8, 2, dropout=0.5)
    for branch in (block.branch1, block.branch2):
        assert isinstance(branch[-1], torch.nn.Dropout) and branch[-1].p == 0.5
        assert isinstance(branch[-2], torch.nn.ReLU)
    x = torch.randn(4, 8, 6, 6)
    block.eval()
    with torch.no_grad():
        assert torch.equal(block(x), block(x))  # no dropout in eval mode
    block.train()
    torch.manual_seed(0)
    with torch.no_grad():
        out = block(x)
    # ReLU outputs are >= 0 and exactly zero only where ReLU clipped or dropout dropped:
    # with p = 0.5 far more than ReLU's zeros are dropped.
    block.branch1[-1].p = block.branch2[-1].p = 0.0
    with torch.no_grad():
        no_drop = block(x)
    assert (out == 0).sum() > (no_drop == 0).sum() + 50


def test_stride_one_block_passes_half_the_channels_through():
    block = InvertedResidual(8, 8, 1).eval()
    x = torch.randn(1, 8, 5, 5)
    with torch.no_grad():
        out = block(x)
    # After the shuffle the untouched first half sits at the even channels.
    assert torch.equal(out[:, 0::2], x[:, :4])


def test_stochastic_depth_only_while_training():
    net = EfficientNetB0Features()
    x = torch.randn(4, 3, 64, 64)
    net.eval()
    with torch.no_grad():
        assert torch.equal(net(x), net(x))
    rates = [m.stochastic_depth.p for stage in net.features[1:8] for m in stage]
    assert rates[0] == 0.0 and max(rates) == pytest.approx(0.2 * 15 / 16)  # torchvision's linear schedule
