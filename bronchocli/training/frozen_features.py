"""Frozen backbone stages computed once per dataset and shared by every cell (``model.frozen_stages``, issue 56).

When the first n stages of both backbones are frozen and identical (pretrained from one file: every run of a sweep
starts its backbones from the same weights), what those stages make of a frame does not depend on the cell, the
seed or the step: it is a function of the frame. :func:`source_for` computes it once for every frame of the
dataset's frame cache (eval mode, fp32, inputs scaled as the network scales them), stores it beside the frame cache
(``frozen-<key>.npy``, written atomically under a lock, so the workers of a sweep build it once between them and
later runs read it), and hands the training loop a :class:`FeatureSource` that gathers those features by frame
index exactly as :class:`~bronchocli.data.batches.FrameSource` gathers frames. The network is told
(``PoseNet.prefix_cached``) to run only its remaining stages. Training, validation and BatchNorm re-estimation
then never run the frozen stages again; the test evaluation runs the whole network on frames (the function the
run ships). The key covers the frame cache, the backbone, the frozen weights' bytes, the input scaling and the
torch version, so anything that would change the features changes the file.

Not used (the frames path as before, said once in the log) when the frozen stages of the two backbones differ
(random initialisation draws each backbone's weights separately), with photometric augmentation (it changes the
frames before the frozen stages), or for backbones without stages (OffsetNet's).
"""

from __future__ import annotations

import hashlib
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data.batches import FrameSource
from ..data.cache import FrameCache
from .. import runkeys
from ..io import atomic_path, file_lock
from .network import PoseRegressor

log = logging.getLogger(__name__)

FEATURES_VERSION = 1  # bump when the stored layout or the computation changes
CHUNK = 64  # frames per forward while computing


def _frozen_state(backbone: torch.nn.Module, n: int) -> list[torch.Tensor]:
    return [t for stage in backbone.stages()[:n] for m in stage for t in (*m.parameters(), *m.buffers())]


def shared_prefix(net: PoseRegressor, n: int, augment: bool) -> str | None:
    """Why the frozen stages cannot be shared (a reason for the log), or None when they can."""
    model = net.model
    if n == 0:
        return "no frozen stages"
    if augment:
        return "data.augment changes the frames before the frozen stages"
    cur, prev = model.backbones()
    if not (hasattr(cur, "stages") and hasattr(cur, "run_stages")):
        return f"{type(cur).__name__} has no stages"
    if not all(torch.equal(a, b) for a, b in zip(_frozen_state(cur, n), _frozen_state(prev, n))):
        return "the two backbones' frozen stages differ (random initialisation draws each separately)"
    return None


def features_key(net: PoseRegressor, cache: FrameCache, n: int) -> str:
    digest = hashlib.sha256(f"v{FEATURES_VERSION}\0{Path(cache.path).name}\0{cache.shape}\0{n}\0"
                            f"{net.model.backbone_kind}\0{torch.__version__}\0".encode())
    for t in (net.image_mean, net.image_std, *_frozen_state(net.model.backbone_cur, n)):
        digest.update(t.detach().float().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


@torch.no_grad()
def compute(net: PoseRegressor, cache: FrameCache, n: int) -> np.ndarray:
    """What the first ``n`` stages of the (current frame's) backbone make of every frame of ``cache``: float32
    ``[N, C, h, w]``, on the CPU, in eval mode."""
    backbone = net.model.backbone_cur
    was = backbone.training
    backbone.eval()
    mean, std = net.image_mean.view(1, 3, 1, 1).cpu(), net.image_std.view(1, 3, 1, 1).cpu()
    parts = []
    try:
        for start in range(0, len(cache), CHUNK):
            frames = torch.from_numpy(cache.take(np.arange(start, min(start + CHUNK, len(cache)))))
            x = (frames.float().div_(255.0) - mean) / std
            parts.append(backbone.run_stages(x, 0, n).float().contiguous().numpy())
    finally:
        backbone.train(was)
    return np.concatenate(parts)


class FeatureSource(FrameSource):
    """The frozen stages' output of the frames, gathered by global frame index (FrameSource's interface)."""

    def __init__(self, features: np.ndarray, device: torch.device | str = "cpu") -> None:
        self.cache, self.device = None, torch.device(device)
        self.bank = torch.from_numpy(features).to(self.device)


def load_or_compute(net: PoseRegressor, cache: FrameCache, n: int) -> tuple[np.ndarray, float]:
    """The features of every frame (from the file beside the frame cache, else computed and stored) and the CPU
    seconds this process spent computing them (0 when read)."""
    path = Path(cache.path).parent / f"frozen-{features_key(net, cache, n)}.npy"
    core_s = 0.0
    if not path.is_file():
        with file_lock(path.with_suffix(".lock")):
            if not path.is_file():  # another worker may have stored it while this one waited
                t0 = time.process_time()
                features = compute(net, cache, n)
                core_s = time.process_time() - t0
                with atomic_path(path) as tmp:
                    with open(tmp, "wb") as fh:
                        np.save(fh, features)
                log.info("frozen stages: computed %s for %d frames in %.1f CPU-s (%s)", features.shape[1:],
                         len(features), core_s, path.name)
                return features, core_s
    return np.load(path), core_s


def source_for(cfg: Any, net: PoseRegressor, cache: FrameCache, device: torch.device,
               frames: FrameSource) -> tuple[FrameSource, dict[str, float]]:
    """The source training reads (features of the frozen stages when they can be shared, else ``frames``), with
    the metrics that say which (``train.frozen_features`` 1/0 and the one-off ``train.frozen_features_core_s``).
    Sets ``net.model.prefix_cached``; :func:`release` sets it back."""
    n = cfg.model.frozen_stages
    why = shared_prefix(net, n, cfg.data.augment)
    if why is not None:
        if n:
            log.info("frozen stages: computed in every step (%s)", why)
        return frames, {runkeys.train("frozen_features"): 0.0} if n else {}
    features, core_s = load_or_compute(net, cache, n)
    net.model.prefix_cached = n
    return FeatureSource(features, device), {runkeys.train("frozen_features"): 1.0,
                                             runkeys.train("frozen_features_core_s"): core_s}


def release(net: PoseRegressor) -> PoseRegressor:
    """The network takes frames again (what it ships and what the test evaluation runs)."""
    net.model.prefix_cached = 0
    return net
