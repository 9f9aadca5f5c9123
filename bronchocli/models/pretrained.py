"""Load torchvision-format ImageNet weights from a local file into a model's two backbones.

Accepted files (``torch.save`` of a state dict, read with ``weights_only=True``;
no download code anywhere):

* an ``efficientnet_b0`` state dict (as torchvision saves it): the ``features.*``
  entries are loaded, ``classifier.*`` is ignored (BronchoPose architectures);
* a ``resnet34`` state dict, ``fc`` included (``offsetnet``).

A mapping that wraps the state dict under ``state_dict`` or ``model`` is
unwrapped. Loading is strict: any missing key, unexpected key or shape mismatch
raises one ``ModelError`` naming the file and the first offending keys. Only
``num_batches_tracked`` may be absent (checkpoints saved before PyTorch 0.4.1,
like torchvision's original ResNet files, lack it; PyTorch fills it in too).
Both backbones receive the same weights (they are then trained separately).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import Tensor

from .base import ModelError, PoseNet

_IGNORED_PREFIXES = {"efficientnet_b0": ("classifier.",), "resnet34": ()}
_SHOW = 5  # offending keys named in the error


def read_state_dict(path: str | os.PathLike) -> dict[str, Tensor]:
    """The tensors of a saved state dict, or a ModelError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"model.pretrained: {path}: file not found")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        lines = str(exc).strip().splitlines()  # torch's refusal of pickled objects is a page of advice: one line
        reason = f"{type(exc).__name__}: {lines[0] if lines else ''}"
        raise ModelError(f"model.pretrained: {path}: not a readable torch state dict ({reason})") from None
    for wrapper in ("state_dict", "model"):
        if isinstance(obj, Mapping) and isinstance(obj.get(wrapper), Mapping):
            obj = obj[wrapper]
    if not isinstance(obj, Mapping) or not all(isinstance(v, Tensor) for v in obj.values()):
        raise ModelError(f"model.pretrained: {path}: expected a state dict (parameter name -> tensor)")
    return dict(obj)


def _first(keys: list[str]) -> str:
    more = f", ... ({len(keys)} in all)" if len(keys) > _SHOW else ""
    return ", ".join(keys[:_SHOW]) + more


def check_compatible(state: Mapping[str, Tensor], expected: Mapping[str, Tensor], kind: str, path: Path) -> None:
    """Raise one ModelError listing the first missing, unexpected and mis-shaped keys, if any."""
    missing = [k for k in expected if k not in state and not k.endswith("num_batches_tracked")]
    unexpected = [k for k in state if k not in expected]
    shapes = [
        f"{k} {list(state[k].shape)} (expected {list(expected[k].shape)})"
        for k in expected
        if k in state and state[k].shape != expected[k].shape
    ]
    problems = [
        f"{len(lst)} {what}: {_first(lst)}"
        for what, lst in (("missing keys", missing), ("unexpected keys", unexpected), ("shape mismatches", shapes))
        if lst
    ]
    if problems:
        raise ModelError(f"model.pretrained: {path}: not a torchvision {kind} state dict: " + "; ".join(problems))


def load_pretrained(model: PoseNet, path: str | os.PathLike) -> PoseNet:
    """Copy the file's weights into both backbones of ``model`` (strict, see module doc)."""
    path = Path(path)
    kind = model.backbone_kind
    state = {k: v for k, v in read_state_dict(path).items() if not k.startswith(_IGNORED_PREFIXES[kind])}
    for backbone in model.backbones():
        expected = backbone.state_dict()
        check_compatible(state, expected, kind, path)
        full = {**{k: v for k, v in expected.items() if k.endswith("num_batches_tracked")}, **state}
        backbone.load_state_dict(full, strict=True)
    return model
