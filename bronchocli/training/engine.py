"""Fit and evaluate one cell: build the network, train it, evaluate the best weights on the test trajectories.

No MLflow here (``artifacts.py`` logs) and no data preparation (``prepare.py``):
this module turns prepared data into a trained network and its test results.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import pandas as pd
import torch

from .. import runkeys
from ..cells import Cell
from ..config import Config
from ..data.batches import FrameSource
from ..models import build_model, input_normalisation
from ..runs.contract import gpu_share
from ..runs.processes import process_age_s
from . import evaluate, frozen_features
from .cost import cost_of_learning
from .device import device_for, precision_for, seed_everything, speed_for
from .loop import FitResult, Settings, Trainer
from .network import PoseRegressor, round_to_export_
from .prepare import RunData, sample_pairs

EVAL_CHUNK = 64  # pairs per forward when evaluating pairwise models


def settings(cfg: Config, cell: Cell, device: torch.device) -> Settings:
    t = cfg.train
    n = sample_pairs(cfg, cell.arch)
    chunk = cfg.data.window if t.tbptt_chunks > 1 and n > 1 else n
    return Settings(
        steps=t.steps, micro_pairs=t.batch_size, accum=t.pairs_per_step // t.batch_size, chunk=chunk,
        val_every=min(t.val_every, t.steps), patience=t.patience, min_delta=t.min_delta, lr=t.lr,
        weight_decay=t.weight_decay, warmup_steps=int(round(t.warmup * t.steps)), schedule=t.schedule,
        rot_loss=cell.rot_loss, rot_weight=t.rot_weight, precision=precision_for(cfg, device, cell.arch),
        bn_recalibrate=t.bn_recalibrate, augment=cfg.data.augment, seed=cell.seed,
        checkpoint_every_s=t.checkpoint_every_s, log_every=cfg.runs.log_every, bn_freeze=t.bn_freeze,
        stop_at_ratio=t.stop_at_ratio, grad_clip=t.grad_clip, backbone_lr=t.backbone_lr,
        rot_scale=t.rot_scale == "label_std",
    )


def build_network(cfg: Config, cell: Cell, data: RunData, device: torch.device) -> PoseRegressor:
    model = build_model(cell.arch, image_size=data.image_size, dropout=cfg.model.dropout,
                        pretrained=cfg.paths.pretrained, backbone=cfg.model.backbone)
    model.freeze_stages(cfg.model.frozen_stages)
    if speed_for(cfg, cell.arch, device).channels_last:
        model = model.to(memory_format=torch.channels_last)
    standardize = cfg.train.standardize_labels
    # a pretrained backbone sees its inputs scaled as its weights were trained; a random one, the training frames'
    image_mean, image_std = (input_normalisation(cfg.paths.pretrained, model.backbone_kind)
                             or (data.image_mean, data.image_std))
    net = PoseRegressor(model, image_mean, image_std,
                        data.label_mean if standardize else (0.0,) * 6,
                        data.label_std if standardize else (1.0,) * 6, standardized=standardize)
    return net.to(device)


def _both(first: Callable[[int, dict[str, float]], None] | None,
          then: Callable[[int, dict[str, float]], None]) -> Callable[[int, dict[str, float]], None]:
    def both(step: int, values: dict[str, float]) -> None:
        if first is not None:
            first(step, values)
        then(step, values)
    return both


@dataclass
class Outcome:
    metrics: dict[str, float]
    fit: FitResult
    predictions: list[evaluate.TrajectoryPrediction]
    trajectories: pd.DataFrame  # per-trajectory errors of the model and the references
    network: PoseRegressor


def fit_and_evaluate(cfg: Config, cell: Cell, data: RunData, *, ckpt_dir: Path | None = None,
                     resume_state: dict[str, Any] | None = None, stop: Any = None,
                     on_validation: Callable[[int, dict[str, float]], None] | None = None,
                     on_step: Callable[[int, int], None] | None = None,
                     on_phase: Callable[[str], None] | None = None,
                     on_curves: Callable[[list[tuple[int, dict[str, float]]]], None] | None = None,
                     threads: Callable[[], int] | None = None) -> Outcome:
    """Train ``cell`` on ``data`` (or continue ``resume_state``) and evaluate the best weights on the test split;
    ``on_phase`` hears what happens after the last step (the test evaluation), ``on_curves`` the training-curve
    points of each validation window; ``threads`` says the torch CPU threads to use, asked at the start, after each
    validation and at every step (``runs.cores``: the share of the machine's cores, re-decided every few seconds)."""
    t_start = time.perf_counter()

    def share_cores(*_: Any) -> None:
        n = threads() if threads is not None else None
        if n is not None and n != torch.get_num_threads():
            torch.set_num_threads(n)

    share_cores()
    device = device_for(cfg)
    seed_everything(cell.seed)
    net = build_network(cfg, cell, data, device)
    source = FrameSource(data.cache, device, cfg.data.frames_on_device, share=gpu_share())
    # frozen backbone stages shared by every cell: computed once per dataset, then read (frozen_features.py)
    train_source, frozen_metrics = frozen_features.source_for(cfg, net, data.cache, device, source)
    first_step: dict[str, float] = {}

    def stepped(step: int, total: int) -> None:
        if not first_step:  # start-up as a user waits through it: imports, data, model, compilation, one step
            first_step["run"] = time.perf_counter() - t_start
            age = process_age_s()
            if age is not None:
                first_step["process"] = age
        share_cores()  # another command started: give back cores within seconds, not at the next validation
        if on_step is not None:
            on_step(step, total)

    trainer = Trainer(net, data.train, data.val, train_source, settings(cfg, cell, device), device=device,
                      ckpt_dir=ckpt_dir, stop=stop, on_validation=_both(on_validation, share_cores), on_step=stepped,
                      compile=cfg.train.compile, cell_key=cell.key, on_curves=on_curves)
    if resume_state is not None:
        trainer.load_state(resume_state)
    fit = trainer.fit()
    frozen_features.release(net)  # the test evaluates the whole network on frames: the function the run ships
    round_to_export_(net, cfg.runs.model_artifact)  # test the weights the run ships (fp16: rounded)
    if on_phase is not None:
        on_phase(f"test evaluation ({len(data.split.test)} trajectories)")
    t0 = time.perf_counter()
    chunk = cfg.data.window if net.temporal else EVAL_CHUNK
    spacing = {p: data.dataset.spacing_mm(p) for p in data.dataset.patients}
    preds = evaluate.predict_trajectories(net, data.split.test, source, cell.pose_frame, chunk, spacing,
                                          trainer.autocast)
    metrics, table = evaluate.evaluate(preds, data.label_mean, cell.pose_frame, evaluate.thresholds(cfg.eval))
    best = next((h for h in fit.history if h["step"] == fit.best_step), None)
    if best is not None:  # validation metrics of the weights that were tested: what a staged sweep selects by
        metrics |= {runkeys.best_of(k): v for k, v in best.items() if k == runkeys.VAL_LOSS or runkeys.val_name(k)}
        if runkeys.VAL_MODE_GAP in best:  # eval-mode ÷ batch-statistics loss on training batches, the tested weights
            metrics[runkeys.evaluation("mode_gap")] = best[runkeys.VAL_MODE_GAP]
    n_params = sum(p.numel() for p in net.model.parameters())
    train = runkeys.train
    metrics |= {
        runkeys.N_PARAMS: float(n_params), runkeys.evaluation("time_s"): time.perf_counter() - t0,
        train("steps"): float(fit.steps), train("pairs_seen"): float(fit.pairs_seen), train("epochs"): fit.epochs,
        train("validations"): float(fit.validations), train("best_step"): float(fit.best_step),
        train("time_s"): fit.train_time_s, train("val_time_s"): fit.val_time_s,
        train("checkpoint_time_s"): fit.checkpoint_time_s,  # this process's (a resumed run: since the resume)
        train("pairs_per_s"): fit.pairs_seen / max(fit.train_time_s, 1e-9) if fit.steps else 0.0,
        train("train_pairs"): float(len(data.train) * data.train.n_pairs),
        train("train_trajectories"): float(len(data.split.train)),
        train("frames_on_device"): float(source.resident),
        train("skipped_steps"): float(trainer.skipped_steps),  # 16-mixed: steps the loss scaler skipped
        train("core_s"): trainer.core_s,  # CPU seconds of the training steps, every thread (a resumed run: all)
        **cost_of_learning(fit.history),
        **frozen_metrics,  # cost.pairs_to_0.90 / cost.core_s_to_0.90 when a validation reached it
    }
    if "run" in first_step:
        metrics[train("first_step_s")] = first_step["run"]  # from the engine's start (data already prepared)
    if "process" in first_step:
        metrics[train("process_first_step_s")] = first_step["process"]  # from the process's start
    return Outcome(metrics, fit, preds, table, net)
