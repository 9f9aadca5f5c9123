"""The training loop: a budget of optimiser steps, validation every N steps, the best weights kept.

Plain PyTorch (no training framework: importing one cost 19 s of start-up on a GPU machine and a host sync per
logged value). One optimiser step consumes ``train.effective_batch`` image pairs for every architecture, so a
budget of ``train.steps`` steps is the same number of pairs seen whatever the model:

* a micro-batch is ``train.batch_size`` pairs: that many independent pairs for
  pairwise models, ``batch_size / L`` windows of L = ``data.window`` pairs for
  temporal ones; gradients accumulate over ``effective_batch / batch_size``
  micro-batches (one back-propagated chunk each) per step;
* truncated BPTT (``train.tbptt_chunks`` = K): a temporal sample holds K·L
  pairs, processed in K chunks of L whose recurrent state is carried but
  detached; each chunk is back-propagated at once and counts as a micro-batch;
* the learning rate warms up linearly over ``train.warmup`` of the steps, then
  follows ``train.schedule`` (cosine decay to zero, or constant); or ``onecycle``:
  one cycle (PyTorch's OneCycleLR with its defaults), rising over the warm-up
  fraction from lr/25 to lr and falling to lr/250,000, Adam's beta1 cycled
  between 0.95 and 0.85 against it;
* every ``train.val_every`` steps (and at the end) BatchNorm statistics are
  re-estimated on ``train.bn_recalibrate`` training batches (running averages
  after a few hundred steps describe weights that no longer exist, and
  eval-mode outputs collapse), the validation loss, ``val.ratio.pos_l2`` (÷ the
  training mean's) and the mode gap (eval-mode ÷ batch-statistics loss on
  training batches, ``batchnorm.py``) are computed, the best weights so far are
  kept and a resumable checkpoint is written; after ``train.patience``
  validations without improvement the run stops early, and with
  ``train.stop_at_ratio`` once ``val.ratio.pos_l2`` reaches that value (the cost
  of learning, ``cost_of_learning``). The run ends on the best weights, whatever
  stopped it;
* ``train.bn_freeze``: the last fraction of the steps trains with BatchNorm in
  eval mode on the statistics re-estimated by a validation held where the
  freeze starts (then no more re-estimation): the evaluated function is the
  trained one.

Losses, metrics and non-finite checks stay on the device between validations: nothing forces a host sync per step
on CUDA. Training curves (``train_loss``, ``lr``, ``grad_norm``, ``pairs_per_s``) get a point every ``log_every``
steps and at every validation: the point's loss sum and gradient norm stay on the device until the validation
(already a host sync) reads them all at once and hands them to ``on_curves``; the learning rate and the clock are
host values. """

from __future__ import annotations

import logging
import math
import signal
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from .. import interrupts, metrics, registry, runkeys
from ..data.batches import BatchOrder, FrameSource, Photometric, Samples
from ..errors import BronchoError
from ..models import detach_state
from ..runs.contract import RESUME_FILE, RunInterrupted, RunTakenOver
from . import checkpoint
from .batchnorm import freeze_bn, mode_gap, recalibrate_bn
from .compiling import compile_network
from .network import PoseRegressor
from .optimiser import optimiser
from .schedule import beta1, lr_factor

log = logging.getLogger(__name__)

CUDA_CHECK_EVERY = 25  # optimiser steps between non-finite checks on CUDA (each check is a host sync)
# 16-mixed loss scaling. Unscaled fp16 gradients of these networks at initialisation reach ~1.5e4 (conv3d,
# lstm: measured on the CPU), so PyTorch's default first scale of 2^16 overflows and halves for ~16 steps
# that are all skipped: a 4-step run trained nothing. Start at 1 and let the scale grow after every
# AMP_GROWTH_INTERVAL clean steps (default 2000: never within the budgets of this project).
AMP_INIT_SCALE = 1.0
AMP_GROWTH_INTERVAL = 100


class NonFiniteLoss(BronchoError):
    """The training loss became NaN or infinite; the run fails with this reason."""


class NothingTrained(NonFiniteLoss):
    """16-mixed: every optimiser step so far had inf/NaN gradients and was skipped by the loss scaler."""


@dataclass(frozen=True)
class Settings:
    """What the loop needs from ``train``/``data`` (see the module doc for the semantics)."""

    steps: int
    micro_pairs: int  # pairs per micro-batch (train.batch_size)
    accum: int  # micro-batches per optimiser step
    chunk: int  # pairs per back-propagated chunk (the whole sample unless TBPTT)
    val_every: int
    patience: int | None
    min_delta: float
    lr: float
    weight_decay: float
    warmup_steps: int
    schedule: str
    rot_loss: str
    rot_weight: float
    precision: str  # "32", "bf16-mixed" or "16-mixed"
    bn_recalibrate: int
    augment: bool
    seed: int
    eval_batch: int = 64  # pairs per validation forward
    checkpoint_every_s: float = math.inf  # seconds between checkpoints by time (train.checkpoint_every_s)
    log_every: int = 0  # optimiser steps between training-curve points (0: a point at each validation only)
    bn_freeze: float = 0.0  # the last fraction of the steps trains with BatchNorm statistics fixed (batchnorm.py)
    mode_gap_batches: int = 4  # training batches of each validation's mode gap (0: not measured)
    stop_at_ratio: float | None = None  # stop once val.ratio.pos_l2 <= this (train.stop_at_ratio)
    grad_clip: float | None = None  # clip the gradients' global L2 norm to this (train.grad_clip)
    backbone_lr: float = 1.0  # the backbones' learning rate as a fraction of the head's (train.backbone_lr)
    rot_scale: bool = False  # a bounded rotation loss in units of one label std (train.rot_scale: label_std)

    @property
    def pairs_per_step(self) -> int:
        return self.micro_pairs * self.accum

    @property
    def freeze_step(self) -> int:
        """The first step trained with BatchNorm statistics fixed (``steps``: never)."""
        return self.steps - int(round(self.bn_freeze * self.steps))


@dataclass
class FitResult:
    steps: int
    pairs_seen: int
    epochs: float  # passes over the training samples
    stop_reason: str  # budget, early_stop, target (train.stop_at_ratio reached)
    best_step: int
    best_val_loss: float
    validations: int
    train_time_s: float
    val_time_s: float
    history: list[dict[str, float]] = field(default_factory=list)
    checkpoint_time_s: float = 0.0  # writing the checkpoints of the validations (outside train/val time)


class Trainer:
    """Fits one :class:`PoseRegressor` on training samples, validating on validation samples."""

    def __init__(self, net: PoseRegressor, train: Samples, val: Samples, source: FrameSource, s: Settings,
                 *, device: torch.device, ckpt_dir: Path | None = None, stop: Any = None,
                 on_validation: Callable[[int, dict[str, float]], None] | None = None,
                 on_step: Callable[[int, int], None] | None = None, compile: bool | str = False,
                 cell_key: str | None = None,
                 on_curves: Callable[[list[tuple[int, dict[str, float]]]], None] | None = None) -> None:
        self.cell_key = cell_key  # written into checkpoints: a resume checks the file is this cell's
        self.net, self.train_set, self.val_set, self.source, self.s = net, train, val, source, s
        # The compiled module shares the network's parameters; state dicts and checkpoints use ``net``.
        self.forward = compile_network(net, compile)
        self.cuda_graphs = compile == "reduce-overhead" and device.type == "cuda"
        self.device, self.ckpt_dir, self.stop = device, ckpt_dir, stop
        self.on_validation, self.on_step, self.on_curves = on_validation, on_step, on_curves
        samples_per_micro = max(1, s.micro_pairs // train.n_pairs)
        self.order = BatchOrder(len(train), samples_per_micro, s.seed)
        self.photometric = Photometric() if s.augment else None
        fused = device.type in ("cuda", "cpu")
        self.opt = optimiser(net, s.lr, s.weight_decay, s.backbone_lr, fused=fused)
        self.sched = torch.optim.lr_scheduler.LambdaLR(self.opt, lambda k: lr_factor(k, s))
        self._beta1 = lambda k: beta1(k, s)  # the schedule's own settings, as the rate's
        self.scaler = torch.amp.GradScaler(device.type, init_scale=AMP_INIT_SCALE,
                                           growth_interval=AMP_GROWTH_INTERVAL, enabled=s.precision == "16-mixed")
        self.check_every = CUDA_CHECK_EVERY if device.type == "cuda" else 1  # non-finite checks (host syncs)
        self.step = 0  # optimiser steps taken
        self._set_beta1()
        self.micro = 0  # training samples batches drawn
        self.backwards = 0  # chunks back-propagated since the last optimiser step
        self.best_val = math.inf
        self.best_step = 0
        self.best_state: dict[str, torch.Tensor] | None = None
        self.bad = 0  # validations without improvement
        self.history: list[dict[str, float]] = []
        self.train_time = self.val_time = self.ckpt_time = 0.0
        self.core_s = 0.0  # CPU seconds (every thread) spent in training steps: the cost of learning (cost.py)
        self._loss_sum = torch.zeros((), device=device)
        self._loss_n = 0
        self._skipped = torch.zeros((), device=device)  # skipped steps since the last validation, on the device
        self._saved_at = time.monotonic()  # when the last checkpoint was written (checkpoints by time)
        # Curve points since the last validation: (step, loss-sum snapshot, chunks, grad norm, lr, pairs/s).
        self._points: list[tuple[int, torch.Tensor, int, torch.Tensor | None, float, float]] = []
        self._clock = (0, time.perf_counter())  # (step, time) of the last curve point or the window's start

    # -- precision ------------------------------------------------------------------------------
    def autocast(self):
        if self.s.precision == "32":
            return torch.autocast(self.device.type, enabled=False)
        dtype = torch.bfloat16 if self.s.precision == "bf16-mixed" else torch.float16
        return torch.autocast(self.device.type, dtype=dtype)

    # -- one optimiser step -----------------------------------------------------------------------
    def _batch(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        ids = self.order(i)
        frames = self.source(self.train_set.frames[ids])
        if self.photometric is not None:
            gen = torch.Generator(device=self.device).manual_seed(self.s.seed * 1_000_003 + i)
            frames = self.photometric(frames, gen)
        labels = torch.from_numpy(self.train_set.labels[ids]).to(self.device, non_blocking=True)
        return frames, labels

    def _backward_chunks(self, frames: torch.Tensor, labels: torch.Tensor) -> Iterator[None]:
        """Forward/backward each chunk of the sample; yields after each back-propagated chunk."""
        state = None
        n = labels.shape[1]
        for start in range(0, n, self.s.chunk):
            if self.cuda_graphs:  # a new iteration: the graphs' previous outputs may be overwritten
                torch.compiler.cudagraph_mark_step_begin()
            with self.autocast():
                out, state = self.forward(frames[:, start: start + self.s.chunk + 1], state)
            loss = self.net.loss(out.float(), labels[:, start: start + self.s.chunk], self.s.rot_loss,
                                 self.s.rot_weight, self.s.rot_scale)
            self.scaler.scale(loss / self.s.accum).backward()
            self._loss_sum += loss.detach()  # a NaN/inf loss makes the sum non-finite: checked in _check_finite
            self._loss_n += 1
            state = detach_state(state)
            yield

    def _grad_norm(self) -> torch.Tensor:
        """The gradients' global L2 norm, unscaled, on the device (inf/NaN when the scaler will skip the step)."""
        grads = [p.grad for p in self.net.parameters() if p.grad is not None]
        norm = torch.nn.utils.get_total_norm(grads) if grads else torch.zeros((), device=self.device)
        if self.scaler.is_enabled():
            norm = norm / self.scaler._scale.float()  # the scale as a tensor: get_scale() would sync
        return norm.float()

    def _set_beta1(self) -> None:
        """Adam's beta1 for the next optimiser step where the schedule cycles it (``onecycle``)."""
        b1 = self._beta1(self.step)
        if b1 is not None:
            for group in self.opt.param_groups:
                group["betas"] = (b1, group["betas"][1])

    def _optimiser_step(self) -> None:
        point = self.s.log_every > 0 and (self.step + 1) % self.s.log_every == 0
        norm = self._grad_norm() if point else None
        lr = self.opt.param_groups[0]["lr"]  # the rate this step uses (a host float)
        if self.s.grad_clip is not None:  # on the unscaled gradients (a skipped step's inf/NaN stay so)
            self.scaler.unscale_(self.opt)
            torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.s.grad_clip, foreach=True)
        self.scaler.step(self.opt)
        if self.scaler.is_enabled():  # counted on the device: fused Adam takes found_inf without a host sync
            for found in self.scaler._found_inf_per_device(self.opt).values():
                self._skipped += found
        self.scaler.update()
        self.opt.zero_grad(set_to_none=True)
        self.sched.step()
        self.step += 1
        self._set_beta1()
        self.backwards = 0
        if point:
            self._point(norm, lr)

    def _point(self, norm: torch.Tensor | None, lr: float) -> None:
        """A training-curve point at this step: device values kept, read at the next validation."""
        now = time.perf_counter()
        last_step, last_time = self._clock
        pairs = (self.step - last_step) * self.s.pairs_per_step
        self._points.append((self.step, self._loss_sum.clone(), self._loss_n, norm, lr,
                             pairs / max(now - last_time, 1e-9)))
        self._clock = (self.step, now)

    def _curves(self) -> list[tuple[int, dict[str, float]]]:
        """The points since the last validation as host values (one transfer), the window's loss as a mean."""
        if not self._points or self._points[-1][0] != self.step:  # every validation ends a point
            self._point(None, self.opt.param_groups[0]["lr"])
        norms = [p[3] if p[3] is not None else torch.full((), math.nan, device=self.device) for p in self._points]
        values = torch.stack([torch.stack([p[1].float() for p in self._points]), torch.stack(norms)]).tolist()
        rows, prev_sum, prev_n = [], 0.0, 0
        for (step, _, n, norm, lr, rate), total, gnorm in zip(self._points, values[0], values[1]):
            row = {"lr": lr, "pairs_per_s": rate}
            if n > prev_n:
                row[runkeys.TRAIN_LOSS] = (total - prev_sum) / (n - prev_n)
            if norm is not None:
                row["grad_norm"] = gnorm
            rows.append((step, row))
            prev_sum, prev_n = total, n
        self._points = []
        return rows

    def _train_until(self, target: int) -> None:
        self.net.train()
        if self.step >= self.s.freeze_step:  # on the statistics re-estimated by the validation at freeze_step
            freeze_bn(self.net)
        self._clock = (self.step, time.perf_counter())  # throughput counts training time only
        while self.step < target:
            frames, labels = self._batch(self.micro)
            self.micro += 1
            for _ in self._backward_chunks(frames, labels):
                self.backwards += 1
                if self.backwards == self.s.accum:
                    self._optimiser_step()
                    self._after_step()
                    if self.step >= target:
                        break

    def _after_step(self) -> None:
        if self.step % self.check_every == 0:
            self._check_finite()
        if self.on_step is not None:
            self.on_step(self.step, self.s.steps)
        if self.stop is not None and self.stop.signal is not None:
            raise self._interrupted(self.stop.signal)
        validates = self.step % self.s.val_every == 0 or self.step >= self.s.steps  # checkpoints there anyway
        due = time.monotonic() - self._saved_at >= self.s.checkpoint_every_s
        if self.ckpt_dir is not None and not validates and due:
            log.info("checkpoint of step %d/%d saved to %s (every %g s)", self.step, self.s.steps,
                     self.save_resume(), self.s.checkpoint_every_s)

    def _interrupted(self, signum: int) -> RunInterrupted:
        """Checkpoint the current step (between two optimiser steps) and say so: the run's KILLED reason."""
        path = self.save_resume()
        where = f"checkpoint of step {self.step} saved to {path}" if path is not None else "no checkpoint folder"
        name = signal.Signals(signum).name
        why = f" ({meaning})" if (meaning := interrupts.meaning(signum)) else ""
        exc = RunInterrupted(f"{name} received at step {self.step}/{self.s.steps}{why}; {where}")
        exc.signal = signum
        log.warning("%s", exc)
        return exc

    def _check_finite(self) -> None:
        if not bool(torch.isfinite(self._loss_sum)):
            raise NonFiniteLoss(f"non-finite training loss by step {self.step}: lower train.lr or check the data")

    # -- validation ---------------------------------------------------------------------------------
    def _recalibrate(self) -> None:
        if self.s.bn_recalibrate <= 0 or self.step > self.s.freeze_step:  # frozen: the statistics it trains with
            return
        # Batches far from the training stream's position, so recalibration does not re-use what was just seen.
        start = 10_000_000 + self.step * 131
        recalibrate_bn(self.net, (self._batch(start + k)[0] for k in range(self.s.bn_recalibrate)), self.autocast)

    @torch.no_grad()
    def validate(self, samples: Samples | None = None) -> dict[str, float]:
        samples = samples or self.val_set
        self.net.eval()
        per = max(1, self.s.eval_batch // samples.n_pairs)
        every = metrics.metric_functions()
        fns = {name: every[name] for name in registry.metric_names(validation=True)}  # val.<m> (registry.py)
        sums = torch.zeros(2 + len(fns), dtype=torch.float64, device=self.device)
        n = 0
        mean = torch.from_numpy(self.train_set.labels.reshape(-1, 6).mean(0)).to(self.device)  # the reference
        for k in range(0, len(samples), per):
            frames = self.source(samples.frames[k: k + per])
            labels = torch.from_numpy(samples.labels[k: k + per]).to(self.device)
            with self.autocast():
                out, _ = self.net(frames)
            out = out.float()
            loss = self.net.loss(out, labels, self.s.rot_loss, self.s.rot_weight, self.s.rot_scale)
            pairs = labels.shape[0] * labels.shape[1]
            vals = [loss] + [fn(out, labels).mean() for fn in fns.values()]
            vals.append(metrics.pos_l2(mean.expand_as(labels), labels).mean())
            sums += torch.stack([v.double() for v in vals]) * pairs
            n += pairs
        means = (sums / max(n, 1)).tolist()  # the one host sync of a validation
        # val.ratio.pos_l2: position error ÷ the training-mean predictor's on the same pairs (the headline, on val)
        val = dict(zip(fns, means[1:-1]))
        return {runkeys.VAL_LOSS: means[0], **{runkeys.val(m): v for m, v in val.items()},
                runkeys.VAL_RATIO: val[runkeys.HEADLINE_METRIC] / means[-1] if means[-1] > 0 else float("nan")}

    def _validation(self) -> bool:
        """Validate, keep the best weights, checkpoint; True when early stopping says stop."""
        t0 = time.perf_counter()
        self._recalibrate()
        values = self.validate()
        if self.s.mode_gap_batches:  # training batches far from the stream's position and the recalibration's
            batches = [self._batch(20_000_000 + k) for k in range(self.s.mode_gap_batches)]
            gap = mode_gap(self.net, batches, lambda out, y: self.net.loss(out, y, self.s.rot_loss, self.s.rot_weight,
                                                                          self.s.rot_scale), self.autocast)
            values |= {runkeys.val(k): v for k, v in gap.items()}
        self._check_finite()
        curves = self._curves()
        train_loss, skipped = torch.stack([self._loss_sum / max(self._loss_n, 1), self._skipped]).tolist()
        self._loss_sum.zero_()
        self._skipped.zero_()
        self._loss_n = 0
        if self.on_curves is not None:
            self.on_curves(curves)
        values |= {runkeys.train("skipped_steps"): float(self._count_skipped(int(skipped))),
                   runkeys.train("pairs_seen"): float(self.step * self.s.pairs_per_step),
                   runkeys.train("epochs"): self.epochs, runkeys.train("core_s"): self.core_s}
        improved = values[runkeys.VAL_LOSS] < self.best_val - self.s.min_delta
        if improved or self.best_state is None:
            self.best_val = min(self.best_val, values[runkeys.VAL_LOSS])
            self.best_step = self.step
            self.best_state = {k: v.detach().to("cpu", copy=True) for k, v in self.net.state_dict().items()}
            self.bad = 0
        else:
            self.bad += 1
        self.history.append({"step": float(self.step), runkeys.TRAIN_LOSS: train_loss, **values})
        self.val_time += time.perf_counter() - t0
        if self.on_validation is not None:
            self.on_validation(self.step, values)
        t0 = time.perf_counter()
        self.save_resume()
        self.ckpt_time += time.perf_counter() - t0
        if self.s.stop_at_ratio is not None and values[runkeys.VAL_RATIO] <= self.s.stop_at_ratio:
            self.stop_reason = "target"
            return True
        return self.s.patience is not None and self.bad >= self.s.patience

    @property
    def skipped_steps(self) -> int:
        """Optimiser steps the loss scaler skipped (inf/NaN gradients) as of the last validation; kept in the
        history, so a resumed run counts the steps skipped before its checkpoint too."""
        return int(self.history[-1].get(runkeys.train("skipped_steps"), 0)) if self.history else 0

    def _count_skipped(self, skipped: int) -> int:
        """The run's skipped steps so far. Said, never silent; a run whose every step was skipped trained nothing."""
        total = self.skipped_steps + skipped
        if not skipped:
            return total
        log.warning("16-mixed: the loss scaler skipped %d of the last optimiser steps (inf/NaN gradients); "
                    "%d of %d so far", skipped, total, self.step)
        # The first steps may be skipped while the scale settles; a run whose every step was skipped by its end,
        # or by the second validation, trained nothing.
        if total >= self.step and (self.step >= self.s.steps or len(self.history) >= 1):
            raise NothingTrained(f"16-mixed: all {self.step} optimiser steps so far had inf/NaN gradients and were "
                                 f"skipped (nothing was trained); use train.precision: bf16-mixed or 32")
        return total

    @property
    def epochs(self) -> float:
        return self.micro / self.order.per_epoch

    # -- the run ----------------------------------------------------------------------------------------
    def fit(self) -> FitResult:
        reason = "budget"
        self.stop_reason = "early_stop"
        self.check_space()  # a full disk fails the run now, not at its first validation
        while self.step < self.s.steps:
            target = min(self.s.steps, (self.step // self.s.val_every + 1) * self.s.val_every)
            if self.step < self.s.freeze_step:  # a validation (and its re-estimation) where the freeze starts
                target = min(target, self.s.freeze_step)
            t0, c0 = time.perf_counter(), time.process_time()
            self._train_until(target)
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            self.train_time += time.perf_counter() - t0
            self.core_s += time.process_time() - c0  # the process's CPU time over every thread, training only
            if self._validation():
                reason = self.stop_reason
                break
        if self.best_state is not None:
            self.net.load_state_dict(self.best_state)
        return FitResult(self.step, self.step * self.s.pairs_per_step, self.epochs, reason, self.best_step,
                         self.best_val, len(self.history), self.train_time, self.val_time, list(self.history),
                         self.ckpt_time)

    # -- checkpoints --------------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """The resumable training state as plain data (see ``checkpoint``); loadable with weights_only=True."""
        return {
            "run_id": self.ckpt_dir.name if self.ckpt_dir is not None else None, "cell_key": self.cell_key,
            "model": self.net.state_dict(), "optimizer": self.opt.state_dict(), "scheduler": self.sched.state_dict(),
            "scaler": self.scaler.state_dict(), "step": self.step, "micro": self.micro,
            "best_val": float(self.best_val), "best_step": int(self.best_step), "best_state": self.best_state,
            "bad": int(self.bad), "history": [dict(h) for h in self.history],
            "times": (float(self.train_time), float(self.val_time)), "rng": checkpoint.rng_state(),
            "core_s": float(self.core_s),
        }

    def load_state(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["model"])
        self.opt.load_state_dict(state["optimizer"])
        self.sched.load_state_dict(state["scheduler"])
        self.scaler.load_state_dict(state["scaler"])
        self.step, self.micro = int(state["step"]), int(state["micro"])
        self._set_beta1()
        self.best_val, self.best_step, self.bad = float(state["best_val"]), int(state["best_step"]), int(state["bad"])
        self.best_state, self.history = state["best_state"], list(state["history"])
        self.train_time, self.val_time = (float(t) for t in state["times"])
        self.core_s = float(state.get("core_s", 0.0))  # checkpoints written before issue 45 lack it
        checkpoint.set_rng_state(state["rng"])

    def expected_checkpoint_bytes(self) -> int:
        """A checkpoint's size once training runs: weights, best weights and two Adam moments (4x the weights)."""
        return 4 * checkpoint.nbytes(self.net.state_dict())

    def check_space(self) -> None:
        """Before training: CheckpointWriteError (one line) when the checkpoint folder cannot hold a checkpoint."""
        if self.ckpt_dir is not None:
            need = checkpoint.SPACE_FACTOR * self.expected_checkpoint_bytes()
            checkpoint.check_space(self.ckpt_dir / RESUME_FILE, need)

    def save_resume(self) -> Path | None:
        if self.ckpt_dir is None:
            return None
        if (owns := getattr(self.stop, "owns", None)) is not None and not owns():  # never overwrite the new owner's
            raise RunTakenOver(f"step {self.step}: another sweep worker took the run over; no checkpoint written")
        path = checkpoint.save(self.ckpt_dir / RESUME_FILE, self.state())
        self._saved_at = time.monotonic()
        return path
