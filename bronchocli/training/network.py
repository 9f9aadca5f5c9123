"""A pose network with its input normalisation and label standardisation: what is trained and shipped.

``PoseRegressor(model, ...)`` is ``models.portable.Regressor`` (the class a
logged MLflow Model ships and rebuilds: uint8 frames ``[B, T, 3, H, W]`` in,
normalised with the training frames' channel mean/std, the architecture's
output ``z`` mapped to relative poses ``mu + sigma * z``, every statistic a
buffer from the training split only) with the paper's loss.
"""

from __future__ import annotations

import torch

from .. import metrics
from ..models import EFFICIENT_BACKBONES, PAPER_BACKBONE, build_model
from ..models.portable import Regressor, restore


class PoseRegressor(Regressor):
    def loss(self, pred: torch.Tensor, gt: torch.Tensor, rot_loss: str, rot_weight: float,
             rot_scale: bool = False) -> torch.Tensor:
        """The paper's loss; with standardised labels its squared errors are in units of the label std, and with
        ``rot_scale`` (train.rot_scale: label_std) a bounded rotation loss too (metrics.pose_loss)."""
        scale = self.label_std if self.standardized else None
        return metrics.pose_loss(pred, gt, rot_loss, rot_weight, scale=scale, rot_scale=rot_scale)


def export(net: PoseRegressor, cell, image_size: int, precision: str = "fp32") -> dict:
    """A self-contained artifact of a trained network: what to build and its weights (fp32 or fp16)."""
    state = {k: (v.half() if precision == "fp16" and v.is_floating_point() else v).detach().cpu()
             for k, v in net.state_dict().items()}
    return {"format": "bronchopose-model", "version": 1, "arch": cell.arch, "image_size": image_size,
            "backbone": getattr(net.model, "backbone_kind", PAPER_BACKBONE),
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
    backbone = payload.get("backbone", PAPER_BACKBONE)  # OffsetNet's is "resnet34": not a choice, its own
    model = build_model(payload["arch"], image_size=int(payload["image_size"]),
                        backbone=backbone if backbone in EFFICIENT_BACKBONES else PAPER_BACKBONE)
    net = PoseRegressor(model, (0.0,) * 3, (1.0,) * 3, standardized=bool(payload["standardized"]))
    return restore(net, payload["state_dict"])
