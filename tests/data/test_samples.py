"""Training windows, pair samples, whole trajectories and augmentation, read through the frame cache."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from tinydata import write_tiny_dataset

from bronchocli import geometry
from bronchocli.data.cache import FrameCache
from bronchocli.data.reader import open_dataset_dir
from bronchocli.data.samples import SequenceDataset, TrajectoryDataset, relative_labels
from bronchocli.data.windows import window_starts
from bronchocli.errors import ConfigError, DataError


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("samples")
    ds = open_dataset_dir(write_tiny_dataset(tmp / "ds", patients=1, lobes=("ur", "bl"), trajectories=3,
                                             frames=12, image_size=16))
    return ds, FrameCache.open_or_build(ds, None, tmp / "cache", progress=False)


@pytest.mark.parametrize("pairs, n, overlap, starts", [
    (11, 4, 0, [0, 4]), (11, 4, 2, [0, 2, 4, 6]), (11, 4, 3, list(range(8))), (11, 11, 0, [0]),
    (11, 12, 0, []), (11, 1, 0, list(range(11))), (3, 2, 1, [0, 1]),
])
def test_window_starts(pairs, n, overlap, starts):
    assert list(window_starts(pairs, n, overlap)) == starts


@pytest.mark.parametrize("n, overlap", [(4, 0), (4, 2), (10, 5)])
def test_windows_hold_consecutive_frames_and_their_relative_poses(setup, n, overlap):
    ds, cache = setup
    data = SequenceDataset(ds.trajectories, cache, n, overlap, frame="camera")
    per_traj = len(window_starts(11, n, overlap))
    assert len(data) == per_traj * len(ds.trajectories)
    previous = None
    for i in range(len(data)):
        item = data[i]
        t = ds.trajectory(item["key"])
        s = item["start"]
        assert item["frames"].dtype == torch.uint8 and item["frames"].shape == (n + 1, 3, 16, 16)
        np.testing.assert_array_equal(item["frames"].numpy(), cache.array[t.frame_index[s: s + n + 1]])
        assert item["labels"].dtype == torch.float32 and item["labels"].shape == (n, 6)
        expected = geometry.relative_trajectory(t.poses[s: s + n + 1], "camera")
        np.testing.assert_allclose(item["labels"].numpy(), expected, rtol=1e-6, atol=1e-4)
        if previous is not None and previous["key"] == item["key"]:
            assert s - previous["start"] == n - overlap  # consecutive windows share `overlap` pairs
            torch.testing.assert_close(item["labels"][:overlap], previous["labels"][n - overlap:])
            torch.testing.assert_close(item["frames"][:overlap + 1], previous["frames"][n - overlap:])
        previous = item


def test_single_pairs_cover_every_pair_once(setup):
    ds, cache = setup
    data = SequenceDataset(ds.trajectories, cache, n_pairs=1)
    assert len(data) == sum(t.n_pairs for t in ds.trajectories)
    seen = {(data[i]["key"], data[i]["start"]) for i in range(len(data))}
    assert len(seen) == len(data)
    item = data[5]
    assert item["frames"].shape == (2, 3, 16, 16) and item["labels"].shape == (1, 6)
    t = ds.trajectory(item["key"])
    np.testing.assert_allclose(item["labels"][0].numpy(), relative_labels(t)[item["start"]], atol=1e-4)


def test_bad_windows_are_clear_errors(setup):
    ds, cache = setup
    with pytest.raises(DataError, match=r"no trajectory has 21 frames .* \(longest: 12 frames\); lower data.window"):
        SequenceDataset(ds.trajectories, cache, n_pairs=20)
    with pytest.raises(ConfigError, match=r"data.overlap: 4: must be .* smaller than the window \(4 pairs\)"):
        SequenceDataset(ds.trajectories, cache, n_pairs=4, overlap=4)
    with pytest.raises(DataError, match=r"no trajectories"):
        SequenceDataset([], cache, n_pairs=4)
    with pytest.raises(ConfigError, match=r"pose frame 'body'"):
        relative_labels(ds.trajectories[0], "body")


def test_augmentation_is_photometric_seeded_and_off_by_default(setup):
    ds, cache = setup
    plain = SequenceDataset(ds.trajectories, cache, 3)
    aug = SequenceDataset(ds.trajectories, cache, 3, augment=True, seed=1)
    again = SequenceDataset(ds.trajectories, cache, 3, augment=True, seed=1)
    a, b, p = aug[2], again[2], plain[2]
    assert a["frames"].dtype == torch.uint8 and a["frames"].shape == p["frames"].shape
    assert not torch.equal(a["frames"], p["frames"])
    torch.testing.assert_close(a["frames"], b["frames"])  # same seed, item and epoch -> same pixels
    torch.testing.assert_close(a["labels"], p["labels"])  # poses untouched
    assert (a["frames"].float() - p["frames"].float()).abs().mean() < 40  # a perturbation, not a new image
    again.set_epoch(1)
    assert not torch.equal(again[2]["frames"], a["frames"])


def test_whole_trajectories_for_evaluation(setup):
    ds, cache = setup
    data = TrajectoryDataset(ds.trajectories, cache, frame="world")
    assert len(data) == len(ds.trajectories)
    item = data[4]
    t = ds.trajectories[4]
    assert item["key"] == t.key and item["frames"].shape == (12, 3, 16, 16)
    np.testing.assert_array_equal(item["frames"].numpy(), cache.array[t.frame_index])
    assert item["poses"].dtype == torch.float64 and torch.equal(item["poses"], torch.from_numpy(t.poses))
    torch.testing.assert_close(item["start"], item["poses"][0])
    acc = geometry.accumulate(item["start"].numpy(), item["labels"].double().numpy(), "world")
    np.testing.assert_allclose(acc[:, :3], t.poses[:, :3], atol=1e-4)


def test_datasets_pickle_small_and_load_in_worker_processes(setup):
    ds, cache = setup
    _ = cache.array  # opened here; must not travel to the workers
    data = SequenceDataset(ds.trajectories, cache, 4, overlap=2, augment=True)
    assert len(pickle.dumps(data)) < 50_000
    loader = torch.utils.data.DataLoader(data, batch_size=5, num_workers=2, shuffle=False)
    batches = list(loader)
    assert sum(len(b["key"]) for b in batches) == len(data)
    assert batches[0]["frames"].shape == (5, 5, 3, 16, 16) and batches[0]["labels"].shape == (5, 4, 6)
    torch.testing.assert_close(batches[1]["frames"][0], data[5]["frames"])  # same augmentation in a worker
