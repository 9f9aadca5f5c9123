"""A pose network with its input normalisation and label standardisation: what is trained and shipped.

``PoseRegressor(model, ...)`` takes uint8 frames ``[B, T, 3, H, W]``, normalises
them with the training frames' channel mean/std, runs the architecture and
maps its output ``z`` to relative poses ``mu + sigma * z``, where ``mu`` and
``sigma`` are the per-component mean and std of the training labels
(``train.standardize_labels``; identity otherwise). Every statistic comes from
the training split only and is stored as a buffer, so a saved state dict
predicts in physical units on its own.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from .. import metrics
from ..models import PoseNet, State, build_model


def _buffer(values: Sequence[float], shape: tuple[int, ...]) -> torch.Tensor:
    return torch.tensor([float(v) for v in values], dtype=torch.float32).view(*shape)


class PoseRegressor(nn.Module):
    def __init__(self, model: PoseNet, image_mean: Sequence[float], image_std: Sequence[float],
                 label_mean: Sequence[float] = (0.0,) * 6, label_std: Sequence[float] = (1.0,) * 6,
                 standardized: bool = False) -> None:
        super().__init__()
        self.model = model
        self.standardized = standardized
        self.register_buffer("image_mean", _buffer(image_mean, (1, 1, 3, 1, 1)))
        self.register_buffer("image_std", _buffer(image_std, (1, 1, 3, 1, 1)))
        self.register_buffer("label_mean", _buffer(label_mean, (6,)))
        self.register_buffer("label_std", _buffer(label_std, (6,)))

    @property
    def temporal(self) -> bool:
        return self.model.temporal

    def forward(self, frames: torch.Tensor, state: State = None) -> tuple[torch.Tensor, State]:
        x = (frames.float().div_(255.0) - self.image_mean) / self.image_std
        z, state = self.model(x, state)
        return z.float() * self.label_std + self.label_mean, state

    def loss(self, pred: torch.Tensor, gt: torch.Tensor, rot_loss: str, rot_weight: float) -> torch.Tensor:
        """The paper's loss; with standardised labels its squared errors are in units of the label std."""
        scale = self.label_std if self.standardized else None
        return metrics.pose_loss(pred, gt, rot_loss, rot_weight, scale=scale)


def export(net: PoseRegressor, cell, image_size: int, precision: str = "fp32") -> dict:
    """A self-contained artifact of a trained network: what to build and its weights (fp32 or fp16)."""
    state = {k: (v.half() if precision == "fp16" and v.is_floating_point() else v).detach().cpu()
             for k, v in net.state_dict().items()}
    return {"format": "bronchopose-model", "version": 1, "arch": cell.arch, "image_size": image_size,
            "pose_frame": cell.pose_frame, "standardized": net.standardized, "state_dict": state}


def round_to_export_(net: PoseRegressor, precision: str) -> PoseRegressor:
    """Round the network's weights and buffers in place to what :func:`export` stores at ``precision``.

    Evaluating after this scores the weights a run ships: with ``fp16`` the test predictions a run logs are
    exactly what its MLflow Model predicts (the computation stays fp32; only the stored values are rounded).
    """
    if precision == "fp16":
        with torch.no_grad():
            for t in [*net.parameters(), *net.buffers()]:
                if t.is_floating_point():
                    t.copy_(t.half().to(t.dtype))
    return net


def load_exported(payload: dict) -> PoseRegressor:
    """The network of :func:`export`'s artifact, in fp32, eval mode, on the CPU."""
    model = build_model(payload["arch"], image_size=int(payload["image_size"]))
    net = PoseRegressor(model, (0.0,) * 3, (1.0,) * 3, standardized=bool(payload["standardized"]))
    net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in payload["state_dict"].items()})
    return net.eval()
