"""The pose networks: BronchoPose's four architectures and OffsetNet, chosen by name.

``build_model(name, image_size=..., dropout=..., pretrained=...)`` is the one
entry point (``pretrained``: None = random, ``"imagenet"`` = torchvision's weights via
PyTorch's hub cache, or a local file; see ``pretrained.py``). The names and
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
from .base import PoseNet, State, detach_state
from .errors import ModelError
from .pretrained import IMAGENET, describe, ensure_weights, load_pretrained


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
) -> PoseNet:
    """A fresh model of architecture ``name``, optionally with backbone weights from a local file."""
    if name not in ARCHITECTURES:
        raise ModelError(f"unknown architecture {name!r} (valid: {', '.join(ARCHITECTURES)})")
    if not isinstance(image_size, int) or not MIN_IMAGE_SIZE <= image_size <= MAX_IMAGE_SIZE:
        raise ModelError(f"image size {image_size!r} is not an integer in [{MIN_IMAGE_SIZE}, {MAX_IMAGE_SIZE}]")
    if not 0.0 <= dropout < 1.0:
        raise ModelError(f"dropout {dropout!r} is not in [0, 1)")
    model = ARCHITECTURES[name](image_size=image_size, dropout=dropout)
    model.name = name
    if pretrained is not None:
        load_pretrained(model, os.fspath(pretrained))
    return model


def backbone_kind(name: str) -> str:
    """What initialises architecture ``name``'s backbones: ``efficientnet_b0`` or ``resnet34`` weights."""
    if name not in ARCHITECTURES:
        raise ModelError(f"unknown architecture {name!r} (valid: {', '.join(ARCHITECTURES)})")
    return ARCHITECTURES[name].backbone_kind


def initialisation(pretrained: str | Path | None, archs: Sequence[str]) -> dict[str, str]:
    """Fetch (or find) the weights of every architecture in ``archs``; arch -> how it is initialised (run tag)."""
    kinds = {a: backbone_kind(a) for a in archs}
    ensure_weights(pretrained, kinds.values())
    return {a: describe(pretrained, k) for a, k in kinds.items()}


__all__ = [
    "ARCHITECTURES",
    "IMAGENET",
    "ModelError",
    "PoseNet",
    "State",
    "backbone_kind",
    "build_model",
    "detach_state",
    "initialisation",
    "load_pretrained",
    "n_params",
]
