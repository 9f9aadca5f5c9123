"""Data preparation, the Lightning trainer, evaluation and artifact logging of one run.

Split from run.py, which owns the MLflow run's life cycle; this module does the
work inside it.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import lightning.pytorch as pl
import numpy as np
import torch
from torch.utils.data import DataLoader

from .. import tracking
from ..config import Cell, Config
from ..errors import BronchoError
from . import evaluate
from .module import PoseModule

log = logging.getLogger(__name__)
PAIR_CHUNK = 64  # pairs per forward when evaluating non-temporal models


class RunStopped(BronchoError):
    """Training stopped on purpose before the end; the MLflow run is marked KILLED with the reason."""


class RunInterrupted(RunStopped):
    """Training was stopped by SIGINT/SIGTERM; the run is KILLED and can be resumed."""

    exit_code = 130


class RunPruned(RunStopped):
    """An observer (the Optuna pruner) stopped the run after an epoch; the run is KILLED, tagged ``pruned``."""


def checkpoint_dir(cfg: Config, run_id: str) -> Path:
    return cfg.resolve(cfg.tracking.checkpoints) / run_id


def accumulation(cfg: Config) -> int:
    """Micro-batches per optimiser step to reach ``train.effective_batch``."""
    eff = cfg.train.effective_batch
    return 1 if not eff else max(1, math.ceil(eff / cfg.train.batch_size))


def cpu_threads(cfg: Config, workers: int = 1) -> int:
    return cfg.train.threads or max(1, (os.cpu_count() or 1) // max(1, workers))


@dataclass
class PreparedData:
    dataset: Any
    split: Any
    cache: Any
    image_size: int
    mean: tuple[float, float, float]
    std: tuple[float, float, float]

    @property
    def fingerprint(self) -> str:
        return self.dataset.fingerprint


@dataclass
class Outcome:
    metrics: dict[str, float]
    train_time_s: float


def prepare_data(cfg: Config, cell: Cell, progress: bool = True) -> PreparedData:
    """Open the dataset, split it for the cell, decode frames into the cache, normalisation stats (train only)."""
    from ..data.cache import channel_stats, input_size, open_frame_cache
    from ..data.reader import open_dataset
    from ..data.splits import make_split

    dataset = open_dataset(cfg)
    split = make_split(dataset, cell.population, cell.fold, cfg.splits)
    cache = open_frame_cache(cfg, dataset, progress=progress)  # decodes every frame: fails early on a bad one
    mean, std = channel_stats(cache, split.frame_indices("train"))
    return PreparedData(dataset, split, cache, input_size(cfg.data.image_size, dataset),
                        tuple(map(float, mean)), tuple(map(float, std)))


def quiet_lightning() -> None:
    """Keep Lightning's start-up chatter (accelerator lines, tips, benign warnings) off the console."""
    import warnings

    for name in ("lightning.pytorch", "lightning.fabric", "lightning"):
        logging.getLogger(name).setLevel(logging.WARNING)
    for message in (r"Checkpoint directory .* exists and is not empty", r".*LeafSpec.*is deprecated",
                    r"The '\w+_dataloader' does not have many workers", r".*litlogger.*"):
        warnings.filterwarnings("ignore", message=message)


def _ignore_sigint(_: int) -> None:
    # Ctrl-C reaches the whole process group: workers must not die before the
    # main process has saved its checkpoint.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _loader(ds, cfg: Config, shuffle: bool, seed: int, cuda: bool) -> DataLoader:
    workers = cfg.data.workers
    # A last training batch of one sample would crash BatchNorm on 1x1 maps:
    # drop the incomplete batch when there is at least one full one.
    # Persistent workers keep the dataset copy they started with, so they would
    # not see set_epoch: augmented data restarts its workers every epoch.
    persistent = workers > 0 and getattr(ds, "augmentation", None) is None
    return DataLoader(
        ds, batch_size=cfg.train.batch_size, shuffle=shuffle, num_workers=workers,
        persistent_workers=persistent, pin_memory=cuda, worker_init_fn=_ignore_sigint if workers else None,
        generator=torch.Generator().manual_seed(seed), drop_last=shuffle and len(ds) >= cfg.train.batch_size,
    )


class _EpochLogger(pl.Callback):
    """Per-epoch metrics to MLflow (step = epoch) and to an optional observer (the tuner's pruner)."""

    def __init__(self, tracking_uri: str, run_id: str, on_epoch: Callable[[int, dict[str, float]], None] | None):
        self.tracking_uri, self.run_id, self.on_epoch = tracking_uri, run_id, on_epoch
        self._t0 = time.perf_counter()

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._t0 = time.perf_counter()
        dataset = getattr(trainer.train_dataloader, "dataset", None)
        if hasattr(dataset, "set_epoch"):  # new augmentation draws each epoch
            dataset.set_epoch(trainer.current_epoch)

    def on_validation_end(self, trainer, pl_module) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        from mlflow.tracking import MlflowClient

        values = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
        values["epoch_time_s"] = time.perf_counter() - self._t0
        tracking.log_metrics(MlflowClient(self.tracking_uri), self.run_id, values, step=trainer.current_epoch)
        if self.on_epoch is not None:
            self.on_epoch(trainer.current_epoch, values)


class _StopOnSignal(pl.Callback):
    """At the first batch end after SIGINT/SIGTERM: save ``last.ckpt`` and stop with RunInterrupted."""

    def __init__(self, flag, ckpt_dir: Path):
        self.flag, self.ckpt_dir = flag, ckpt_dir

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.flag.signal is None:
            return
        path = self.ckpt_dir / "last.ckpt"
        trainer.save_checkpoint(path)
        name = signal.Signals(self.flag.signal).name
        raise RunInterrupted(f"{name} received at epoch {trainer.current_epoch}, step {trainer.global_step}; "
                             f"checkpoint saved to {path}")


def _precision(cfg: Config, cuda: bool) -> str:
    if cfg.train.precision != "auto":
        return cfg.train.precision
    if cuda:
        return "bf16-mixed" if torch.cuda.is_bf16_supported() else "16-mixed"
    return "32"


def _build(cfg: Config, cell: Cell, data: PreparedData):
    from ..models import build_model

    pretrained = cfg.resolve(cfg.model.pretrained) if cfg.model.pretrained else None
    model = build_model(cell.arch, image_size=data.image_size, dropout=cfg.model.dropout, pretrained=pretrained)
    if cfg.model.channels_last:
        model = model.to(memory_format=torch.channels_last)
    return PoseModule(
        model, rot_loss=cell.rot_loss, rot_weight=cfg.train.rot_weight, lr=cfg.train.lr,
        weight_decay=cfg.train.weight_decay, lr_decay=cfg.train.lr_decay, window=cfg.data.window,
        chunks=cfg.train.tbptt_chunks if model.temporal else 1, accum=accumulation(cfg),
        mean=data.mean, std=data.std,
    )


def _datasets(cfg: Config, cell: Cell, data: PreparedData, temporal: bool):
    from ..data.samples import SequenceDataset

    n_pairs = cfg.data.window * cfg.train.tbptt_chunks if temporal else 1
    overlap = min(cfg.data.overlap, n_pairs - 1) if temporal else 0
    train = SequenceDataset(data.split.train, data.cache, n_pairs, overlap, cell.pose_frame,
                            augment=cfg.data.augment, seed=cell.seed)
    val = SequenceDataset(data.split.val, data.cache, n_pairs, overlap, cell.pose_frame)
    if cfg.train.max_val_pairs and len(val) * n_pairs > cfg.train.max_val_pairs:
        # the same evenly spread samples every epoch, so validation losses stay comparable
        keep = max(1, cfg.train.max_val_pairs // n_pairs)
        val = _Subset(val, np.linspace(0, len(val) - 1, keep).round().astype(int).tolist())
    return train, val


class _Subset(torch.utils.data.Subset):
    @property
    def n_pairs(self) -> int:
        return self.dataset.n_pairs


def _check_sizes(train_ds, val_ds, cell: Cell) -> None:
    from ..errors import DataError

    what = "windows" if train_ds.n_pairs > 1 else "pairs"
    if len(train_ds) < 2 or len(val_ds) < 1:
        raise DataError(
            f"{cell.label}: the split gives {len(train_ds)} training and {len(val_ds)} validation {what} of "
            f"{train_ds.n_pairs} pair(s); need >= 2 and >= 1 (longer trajectories, more trajectories or a smaller "
            f"data.window)")


def _batch_cap(max_pairs: int | None, cfg: Config, ds) -> int | None:
    """``train.max_*_pairs`` in batches of this dataset (a batch holds batch_size x n_pairs pairs)."""
    if max_pairs is None:
        return None
    return max(1, math.ceil(max_pairs / (cfg.train.batch_size * ds.n_pairs)))


def _trainer(cfg: Config, callbacks: list, progress: bool, cuda: bool, train_batches: int | None) -> pl.Trainer:
    if progress:
        from lightning.pytorch.callbacks import RichProgressBar

        callbacks = [*callbacks, RichProgressBar(leave=True)]
    devices = cfg.train.devices if cuda else 1
    accelerator = "cpu" if cfg.train.device == "cpu" else ("auto" if cfg.train.device == "auto" else cfg.train.device)
    return pl.Trainer(
        accelerator=accelerator, devices=devices, strategy="ddp_spawn" if devices > 1 else "auto",
        precision=_precision(cfg, cuda), max_epochs=cfg.train.max_epochs, min_epochs=cfg.train.min_epochs,
        limit_train_batches=train_batches, num_sanity_val_steps=0, logger=False,
        enable_progress_bar=progress, enable_model_summary=False, callbacks=callbacks,
        deterministic=True if not cuda else "warn", default_root_dir=None,
    )


def train_and_evaluate(cfg: Config, cell: Cell, data: PreparedData, client, run_id: str, *, stop, resumed: bool,
                       progress: bool, on_epoch=None) -> Outcome:
    from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint

    quiet_lightning()
    pl.seed_everything(cell.seed, workers=True, verbose=False)
    torch.set_num_threads(cpu_threads(cfg))
    cuda = torch.cuda.is_available() and cfg.train.device in ("auto", "cuda")
    ckpt_dir = checkpoint_dir(cfg, run_id)
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    manifest = ckpt_dir / "split_manifest.csv"
    data.split.write_manifest(manifest)
    if not resumed:
        client.log_artifact(run_id, str(manifest))
    module = _build(cfg, cell, data)
    train_ds, val_ds = _datasets(cfg, cell, data, module.model.temporal)
    _check_sizes(train_ds, val_ds, cell)
    # best: weights only (for evaluation); last: full state (for --resume), removed once the run FINISHED.
    best = ModelCheckpoint(dirpath=ckpt_dir, filename="best", monitor="val_loss", mode="min", save_top_k=1,
                           save_weights_only=True, enable_version_counter=False)
    callbacks = [
        best,
        ModelCheckpoint(dirpath=ckpt_dir, filename="last", save_top_k=1, enable_version_counter=False),
        EarlyStopping(monitor="val_loss", mode="min", patience=cfg.train.patience, min_delta=cfg.train.min_delta),
        _EpochLogger(cfg.tracking_uri, run_id, on_epoch),
        _StopOnSignal(stop, ckpt_dir),
    ]
    trainer = _trainer(cfg, callbacks, progress, cuda, _batch_cap(cfg.train.max_train_pairs, cfg, train_ds))
    last = ckpt_dir / "last.ckpt"
    n_params = sum(p.numel() for p in module.model.parameters())
    t0 = time.perf_counter()
    try:
        trainer.fit(module, _loader(train_ds, cfg, True, cell.seed, cuda), _loader(val_ds, cfg, False, 0, cuda),
                    ckpt_path=str(last) if resumed and last.is_file() else None)
    except (KeyboardInterrupt, SystemExit) as exc:  # Lightning's own SIGTERM/Ctrl-C exits
        raise RunInterrupted(f"training interrupted ({type(exc).__name__}); last epoch checkpoint: {last}") from None
    train_time = time.perf_counter() - t0
    if stop.signal is not None:
        raise RunInterrupted(f"{signal.Signals(stop.signal).name} received; checkpoint: {last}")
    metrics = _evaluate_best(cfg, cell, data, module, best.best_model_path or str(last), client, run_id)
    last.unlink(missing_ok=True)  # optimiser state is only needed to resume an unfinished run
    if cfg.tracking.log_checkpoint:  # the weights now live in MLflow as checkpoint/model.pt
        Path(best.best_model_path).unlink(missing_ok=True)
    metrics |= {
        "n_params": float(n_params), "train.time_s": train_time, "train.epochs": float(trainer.current_epoch),
        "train.pairs_per_s": module.pairs_seen / max(train_time, 1e-9),
        "train.step_time_s": module.step_time,
        "train.val_time_s": module.val_time,
        "best_val_loss": float(best.best_model_score) if best.best_model_score is not None else float("nan"),
    }
    tracking.log_metrics(client, run_id, metrics)
    return Outcome(metrics, train_time)


def _evaluate_best(cfg: Config, cell: Cell, data: PreparedData, module: PoseModule, ckpt: str, client,
                   run_id: str) -> dict[str, float]:
    from ..data.samples import TrajectoryDataset
    from ..plots import save_figure, trajectory_figure

    state = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]
    module.load_state_dict(state)
    module = module.to("cuda" if torch.cuda.is_available() and cfg.train.device in ("auto", "cuda") else "cpu")
    t0 = time.perf_counter()
    items = TrajectoryDataset(data.split.test, data.cache, cell.pose_frame)
    chunk = cfg.data.window if module.model.temporal else PAIR_CHUNK
    described = (
        {**items[i], "patient": t.patient, "lobe": t.lobe, "traj_id": t.traj_id,
         "spacing_mm": data.dataset.spacing_mm(t.patient)}
        for i, t in enumerate(data.split.test)
    )
    preds = evaluate.predict_trajectories(module, described, cell.pose_frame, chunk)
    metrics = evaluate.score(preds, cell.pose_frame)
    zero = evaluate.zero_motion_score(preds, cell.pose_frame)
    metrics |= {f"zero_motion.{k}": v for k, v in zero.items() if k.startswith(("pair.pos_l2.", "acc.pos_l2."))}
    metrics["eval.time_s"] = time.perf_counter() - t0
    # Artifacts are written to a scratch folder and copied into the MLflow store by log_artifact.
    with tempfile.TemporaryDirectory(prefix="bronchopose-") as tmp:
        out = Path(tmp)
        evaluate.predictions_table(preds).to_csv(out / "predictions.csv", index=False)
        client.log_artifact(run_id, str(out / "predictions.csv"))
        shown = preds[:6]
        fig = trajectory_figure([p.gt_abs for p in shown], {cell.arch: [p.pred_abs for p in shown]},
                                titles=[p.key for p in shown])
        for path in save_figure(fig, out / "trajectories"):
            client.log_artifact(run_id, str(path))
        if cfg.tracking.log_checkpoint:
            torch.save({"arch": cell.arch, "image_size": data.image_size, "mean": data.mean, "std": data.std,
                        "pose_frame": cell.pose_frame, "state_dict": module.model.state_dict()}, out / "model.pt")
            client.log_artifact(run_id, str(out / "model.pt"), "checkpoint")
    return metrics
