"""The LightningModule: normalisation, loss, truncated BPTT with gradient accumulation, Adam + LR decay.

Truncated back-propagation through time (``train.tbptt_chunks`` = K): a training
sample of a temporal model holds K·L consecutive image pairs (L =
``data.window``). It is processed in K chunks of L pairs; the recurrent state is
carried from chunk to chunk but detached, so gradients flow back at most L
pairs. Each chunk's loss is back-propagated at once (only one chunk's graph is
alive) and the optimiser steps after every ``accum`` back-propagated chunks,
where ``accum = ceil(effective_batch / batch_size)`` (1 without
``effective_batch``). K = 1 reduces to independent windows with plain gradient
accumulation; K > 1 and accum = 1 is the classic TBPTT of Lightning 1.x.
"""

from __future__ import annotations

import math
import time
from typing import Any

import lightning.pytorch as pl
import torch

from .. import metrics
from ..errors import BronchoError
from ..models import detach_state

VAL_METRICS = ("pos_l2", "rot_l2", "de", "ce")


class NonFiniteLoss(BronchoError):
    """The training loss became NaN or infinite; the run fails with this reason."""


class PoseModule(pl.LightningModule):
    def __init__(
        self,
        model: torch.nn.Module,
        *,
        rot_loss: str,
        rot_weight: float = 1.0,
        lr: float = 1e-4,
        weight_decay: float = 0.0,
        lr_decay: float = 1.0,
        window: int = 1,
        chunks: int = 1,
        accum: int = 1,
        mean: tuple[float, float, float] = (0.5, 0.5, 0.5),
        std: tuple[float, float, float] = (0.25, 0.25, 0.25),
    ) -> None:
        super().__init__()
        self.automatic_optimization = False  # TBPTT + accumulation are done by hand, see module doc
        self.model = model
        self.rot_loss, self.rot_weight = rot_loss, rot_weight
        self.lr, self.weight_decay, self.lr_decay = lr, weight_decay, lr_decay
        self.window, self.chunks, self.accum = window, chunks, max(1, accum)
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 1, 3, 1, 1))
        self._backwards = 0  # chunks back-propagated since the last optimiser step
        self.pairs_seen = 0  # training pairs processed by this process (throughput figure)
        self.step_time = 0.0  # seconds inside training steps (forward, backward, optimiser)
        self.val_time = 0.0  # seconds inside validation steps

    # -- inputs ---------------------------------------------------------------
    def prepare(self, frames: torch.Tensor) -> torch.Tensor:
        """uint8 frames ``[B, T, 3, H, W]`` -> normalised float on this device."""
        x = frames.to(self.device, non_blocking=True).float().div_(255.0)
        return (x - self.mean) / self.std

    def forward(self, frames: torch.Tensor, state: Any = None) -> tuple[torch.Tensor, Any]:
        return self.model(self.prepare(frames), state)

    # -- training -------------------------------------------------------------
    def _check_finite(self, loss: torch.Tensor) -> None:
        if not torch.isfinite(loss):
            raise NonFiniteLoss(
                f"non-finite training loss ({loss.item()}) at epoch {self.current_epoch}, "
                f"step {self.global_step}: lower train.lr or check the data"
            )

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        t0 = time.perf_counter()
        x = self.prepare(batch["frames"])
        labels = batch["labels"].to(self.device).float()
        n_pairs = labels.shape[1]
        chunk = n_pairs if self.chunks == 1 else self.window
        opt = self.optimizers()
        state, total, parts = None, 0.0, 0
        for start in range(0, n_pairs, chunk):
            out, state = self.model(x[:, start : start + chunk + 1], state)
            loss = metrics.pose_loss(out.float(), labels[:, start : start + chunk], self.rot_loss, self.rot_weight)
            self._check_finite(loss)
            self.manual_backward(loss / self.accum)
            self._backwards += 1
            if self._backwards % self.accum == 0:
                self._step(opt)
            state = detach_state(state)
            total, parts = total + loss.detach(), parts + 1
        self.pairs_seen += labels.shape[0] * n_pairs
        self.step_time += time.perf_counter() - t0
        self.log("train_loss", total / parts, on_step=False, on_epoch=True, prog_bar=True, batch_size=labels.shape[0])

    def _step(self, opt) -> None:
        opt.step()
        opt.zero_grad(set_to_none=True)
        self._backwards = 0

    def on_train_epoch_end(self) -> None:
        if self._backwards:  # flush a partial accumulation group so no gradient is lost
            self._step(self.optimizers())
        sched = self.lr_schedulers()
        if sched is not None:
            sched.step()
        self.log("lr", self.optimizers().param_groups[0]["lr"], on_epoch=True)

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        t0 = time.perf_counter()
        out, _ = self(batch["frames"])
        labels = batch["labels"].to(self.device).float()
        out = out.float()
        n = labels.shape[0]
        self.log("val_loss", metrics.pose_loss(out, labels, self.rot_loss, self.rot_weight), prog_bar=True, batch_size=n)
        for name in VAL_METRICS:
            self.log(f"val.{name}", metrics.METRICS[name](out, labels).mean(), batch_size=n)
        self.val_time += time.perf_counter() - t0

    def configure_optimizers(self):
        # The fused kernel is ~5x faster than the per-tensor loop on CPU (benchmarks/README.md).
        opt = torch.optim.Adam(self.model.parameters(), lr=self.lr, weight_decay=self.weight_decay, fused=True)
        if math.isclose(self.lr_decay, 1.0):
            return opt
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=self.lr_decay)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}
