"""Frozen backbone stages computed once per dataset and shared (training/frozen_features.py, issue 56).

What the network computes from cached features equals what it computes from frames; the file is built once and
read after; random initialisation (two different frozen prefixes) and augmentation keep the frames path; a run
trained on cached features records it and ships a network that takes frames.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli import runkeys
from bronchocli.config import load_config
from bronchocli.data.batches import FrameSource
from bronchocli.data.cache import FrameCache
from bronchocli.models import build_model
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import search_runs
from bronchocli.training import frozen_features
from bronchocli.training.network import PoseRegressor
from bronchocli.training.run import run_cell


def _cache(tmp_path, n: int = 10, size: int = 64) -> FrameCache:
    frames = np.random.default_rng(0).integers(0, 256, (n, 3, size, size), dtype=np.uint8)
    path = tmp_path / "frames-test.npy"
    np.save(path, frames)
    return FrameCache(path, frames.shape)


def _net(frozen: int, pretrained: str | None = "imagenet") -> PoseRegressor:
    torch.manual_seed(0)
    model = build_model("convlstm", image_size=64, backbone="efficientnet_lite0", pretrained=pretrained)
    model.freeze_stages(frozen)
    return PoseRegressor(model, (0.5, 0.4, 0.3), (0.2, 0.25, 0.3)).eval()


@pytest.mark.parametrize("n", [4, 9])
def test_the_network_on_cached_features_computes_what_it_computes_on_frames(tmp_path, n):
    cache, net = _cache(tmp_path), _net(n)
    index = np.array([[0, 1, 2, 3], [5, 6, 7, 8]])
    with torch.no_grad():
        want, _ = net(FrameSource(cache)(index))
        features, _ = frozen_features.load_or_compute(net, cache, n)
        net.model.prefix_cached = n
        got, _ = net(frozen_features.FeatureSource(features)(index))
        frozen_features.release(net)
        again, _ = net(FrameSource(cache)(index))
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)
    assert torch.equal(again, want)


def test_the_features_are_computed_once_and_read_after(tmp_path):
    cache, net = _cache(tmp_path), _net(9)
    first, core_s = frozen_features.load_or_compute(net, cache, 9)
    assert core_s > 0 and first.shape == (10, 1280, 2, 2)
    files = list(tmp_path.glob("frozen-*.npy"))
    assert len(files) == 1
    second, core_s = frozen_features.load_or_compute(net, cache, 9)
    assert core_s == 0 and np.array_equal(first, second)
    frozen_features.load_or_compute(net, cache, 4)  # other stages frozen: another file
    assert len(list(tmp_path.glob("frozen-*.npy"))) == 2


def test_random_initialisation_and_augmentation_keep_the_frames_path(tmp_path):
    cache = _cache(tmp_path)
    random_net = _net(9, pretrained=None)
    assert "differ" in frozen_features.shared_prefix(random_net, 9, augment=False)
    assert "augment" in frozen_features.shared_prefix(_net(9), 9, augment=True)
    assert frozen_features.shared_prefix(_net(9), 9, augment=False) is None
    offsetnet = PoseRegressor(build_model("offsetnet", image_size=64), (0.5,) * 3, (0.2,) * 3)
    assert "stages" in frozen_features.shared_prefix(offsetnet, 1, augment=False)


@pytest.mark.heavy
def test_a_run_on_cached_features_records_it_and_ships_a_network_on_frames(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    path = write_config(tmp_path)
    path.write_text(path.read_text().replace(
        "model: {dropout: 0.1}", "model: {dropout: 0.1, backbone: efficientnet_lite0, pretrained: imagenet, frozen_stages: 9}"))
    cfg = load_config(path)
    run_cell(cfg, cfg.cell(arch="convlstm", rot_loss="ce", population="personalized"), progress=False)
    client = client_for(cfg)
    (run,) = [r for r in search_runs(client, [experiment_id(client, cfg)]) if r.info.status == "FINISHED"]
    assert run.data.metrics[runkeys.train("frozen_features")] == 1.0
    assert run.data.metrics[runkeys.train("frozen_features_core_s")] > 0
    assert run.data.params["model.frozen_stages"] == "9"
    assert len(list((tmp_path / "runs" / "cache").glob("frozen-*.npy"))) == 1
