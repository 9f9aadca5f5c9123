"""Where and how a run computes: the device, TF32, the per-architecture speed setting (precision, memory
format), the seed, and the tags that record them. No MLflow and no data here, so ``profile --speed`` and
``selftest`` run on a GPU machine that has torch alone (plus pydantic for the config types).
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch

from .. import speed
from ..config import Config
from ..errors import BronchoError


class DeviceUnavailable(BronchoError):
    """``train.device`` names a device this machine does not have (one line, exit 2, before any MLflow run)."""


def _fp32_flags() -> tuple[Any, ...]:
    """Where torch keeps the TF32 switches (matmuls, cuDNN convolutions, cuDNN RNNs); the new API only:
    mixing it with the legacy ``allow_tf32`` flags makes torch raise."""
    return (torch.backends.cuda.matmul, torch.backends.cudnn.conv, torch.backends.cudnn.rnn)


def set_tf32(enabled: bool) -> None:
    for flags in _fp32_flags():
        flags.fp32_precision = "tf32" if enabled else "ieee"


@contextmanager
def exact_fp32() -> Iterator[None]:
    """fp32 matmuls and convolutions in full precision (no TF32) inside the block: what a CUDA-vs-CPU
    comparison needs, since cuDNN uses TF32 for fp32 convolutions by default (10-bit mantissa, ~1e-3)."""
    saved = [flags.fp32_precision for flags in _fp32_flags()]
    set_tf32(False)
    try:
        yield
    finally:
        for flags, value in zip(_fp32_flags(), saved):
            flags.fp32_precision = value


def _mps_available() -> bool:
    mps = getattr(torch.backends, "mps", None)
    return bool(mps and mps.is_available())


def device_for(cfg: Config) -> torch.device:
    """The run's device: ``auto`` picks cuda > mps > cpu; an explicit device this machine lacks is an error."""
    want = cfg.train.device
    if want == "cuda" and not torch.cuda.is_available():
        raise DeviceUnavailable(f"train.device: cuda, but torch {torch.__version__} sees no CUDA device here "
                                f"(built for CUDA {torch.version.cuda or 'none'}); use train.device: auto or cpu")
    if want == "mps" and not _mps_available():
        raise DeviceUnavailable("train.device: mps, but this machine has no MPS device; use auto or cpu")
    if want in ("auto", "cuda") and torch.cuda.is_available():
        # Fixed input shapes: let cuDNN pick the fastest kernels once; TF32 for fp32 matmuls and convolutions.
        torch.backends.cudnn.benchmark = True
        set_tf32(True)
        return torch.device("cuda")
    if want == "mps" or (want == "auto" and _mps_available()):
        return torch.device("mps")
    return torch.device("cpu")


def bf16_fast(device: torch.device) -> bool:
    """Whether ``device`` runs bf16 natively (CUDA: Ampere or newer; CPU: avx512_bf16 or AMX in oneDNN)."""
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    if device.type == "cpu":
        probe = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
        return bool(probe and probe())
    return False


def device_key(device: torch.device) -> str:
    """The key of ``device`` in a speed settings file: ``cuda:<GPU name>``, ``mps``, or this CPU's vector
    instructions (``speed.cpu_key``: ``cpu:AVX512+bf16``, ``cpu:AVX2``, ...)."""
    if device.type == "cuda":
        return f"cuda:{torch.cuda.get_device_name(device)}"
    return speed.cpu_key() if device.type == "cpu" else device.type


def speed_for(cfg: Config, arch: str, device: torch.device) -> speed.SpeedSetting:
    """Precision and memory format of ``arch`` on ``device``: the config's when explicit, else the measured
    per-architecture setting for this device (``bronchocli/speed.py``), else the defaults."""
    return speed.choose(arch, device_key(device), cfg.train.precision, cfg.model.channels_last,
                        path=cfg.paths.speed_settings, bf16_ok=bf16_fast(device), frozen=cached_prefix(cfg, arch))


def cached_prefix(cfg: Config, arch: str) -> str | None:
    """The speed settings' name of the training ``arch`` does under ``cfg`` when it runs on a cached frozen prefix
    (``speed.frozen_key``), else None: frozen stages, a pretrained start (both backbones from one file, so their
    prefixes are equal: ``frozen_features.shared_prefix``), no photometric augmentation. An architecture whose
    backbone has no stages (OffsetNet) has no such measurement and gets its whole network's."""
    if not cfg.model.frozen_stages or cfg.paths.pretrained is None or cfg.data.augment:
        return None
    return speed.frozen_key(cfg.model.backbone, cfg.model.frozen_stages)


def precision_for(cfg: Config, device: torch.device, arch: str) -> str:
    return speed_for(cfg, arch, device).precision


def device_name(device: torch.device) -> str:
    """The accelerator's name (``NVIDIA H100 80GB HBM3``), or ``none`` on the CPU."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return "Apple MPS" if device.type == "mps" else "none"


def env_tags(cfg: Config, device: torch.device, arch: str) -> dict[str, str]:
    """``env.device``, ``env.precision``, ``env.gpu_name``: where and how a run actually trained."""
    precision = precision_for(cfg, device, arch)
    if precision == "32" and device.type == "cuda":
        precision = "32 (tf32 matmuls and convolutions)"
    return {"env.device": device.type, "env.precision": precision, "env.gpu_name": device_name(device)}


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
