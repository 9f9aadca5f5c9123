"""The optimiser a training run steps: Adam (AdamW with weight decay) over the trainable parameters, the backbones
in a group of their own when ``train.backbone_lr`` sets them a fraction of the head's rate."""

from __future__ import annotations

from typing import Any

import torch


def param_groups(net: torch.nn.Module, lr: float, backbone_lr: float) -> list[dict[str, Any]]:
    """What the optimiser updates: the head at ``lr`` first (its rate is the one logged), then the backbones at
    ``lr * backbone_lr`` (``train.backbone_lr``; one group when it is 1). Frozen parameters (``model.frozen_stages``)
    are left out. The schedule scales every group's rate alike, so the ratio holds at every step."""
    trainable = [p for p in net.parameters() if p.requires_grad]
    model = getattr(net, "model", net)
    backbones = getattr(model, "backbones", lambda: ())()
    in_backbones = {id(p) for b in backbones for p in b.parameters()}
    if backbone_lr == 1.0 or not in_backbones:
        return [{"params": trainable}]
    head = [p for p in trainable if id(p) not in in_backbones]
    body = [p for p in trainable if id(p) in in_backbones]
    if not body:  # the whole backbone frozen
        return [{"params": head}]
    return [{"params": head, "lr": lr}, {"params": body, "lr": lr * backbone_lr}]


def optimiser(net: torch.nn.Module, lr: float, weight_decay: float, backbone_lr: float = 1.0, *,
              fused: bool = False) -> torch.optim.Optimizer:
    """Adam over :func:`param_groups` (AdamW, decoupled, when ``weight_decay`` > 0)."""
    groups = param_groups(net, lr, backbone_lr)
    if weight_decay:
        return torch.optim.AdamW(groups, lr=lr, weight_decay=weight_decay, fused=fused)
    return torch.optim.Adam(groups, lr=lr, fused=fused)
