"""Samples as index arrays (windows of image pairs), their batch order, the frames they point at, augmentation.

References are independent of the code under test: window starts by a plain
loop, labels pair by pair with ``geometry.relative_pose``, frames decoded from
the PNG files with Pillow.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from PIL import Image
from tinydata import write_tiny_dataset

from bronchocli import geometry
from bronchocli.data.batches import BatchOrder, FrameSource, Photometric, Samples, relative_labels, windows
from bronchocli.data.cache import FrameCache
from bronchocli.data.reader import open_dataset_dir
from bronchocli.data.windows import window_starts
from bronchocli.errors import ConfigError, DataError

FRAMES = 12  # per trajectory: 11 image pairs


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("batches")
    ds = open_dataset_dir(write_tiny_dataset(tmp / "ds", patients=1, lobes=("ur", "bl"), trajectories=3,
                                             frames=FRAMES, image_size=16))
    return ds, FrameCache.open_or_build(ds, None, tmp / "cache", progress=False)


def png_frame(path: str) -> np.ndarray:
    """The frame as written on disk, channel-first (what the cache must hold at the dataset's own size)."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB")).transpose(2, 0, 1)


def expected_starts(pairs: int, n: int, overlap: int) -> list[int]:
    out, s = [], 0
    while s + n <= pairs:
        out.append(s)
        s += n - overlap
    return out


def shortened(t, frames: int):
    return dataclasses.replace(t, traj_id=f"{t.traj_id}-short", poses=t.poses[:frames],
                               frame_index=t.frame_index[:frames], filenames=t.filenames[:frames])


# -- window placement ---------------------------------------------------------------------------


@pytest.mark.parametrize("pairs, n, overlap, starts", [
    (11, 4, 0, [0, 4]), (11, 4, 2, [0, 2, 4, 6]), (11, 4, 3, list(range(8))), (11, 11, 0, [0]),
    (11, 12, 0, []), (11, 1, 0, list(range(11))), (3, 2, 1, [0, 1]),
])
def test_window_starts(pairs, n, overlap, starts):
    assert list(window_starts(pairs, n, overlap)) == starts == expected_starts(pairs, n, overlap)


# -- windows() ------------------------------------------------------------------------------------


@pytest.mark.parametrize("frame", ["world", "camera"])
@pytest.mark.parametrize("n, overlap", [(1, 0), (4, 0), (4, 2), (10, 5), (11, 0)])
def test_windows_hold_consecutive_frames_and_their_relative_poses(setup, n, overlap, frame):
    ds, _ = setup
    s = windows(ds.trajectories, n, overlap, frame)
    starts = expected_starts(FRAMES - 1, n, overlap)
    assert isinstance(s, Samples) and len(s) == len(starts) * len(ds.trajectories) and s.n_pairs == n
    assert s.frames.dtype == np.int64 and s.frames.shape == (len(s), n + 1)
    assert s.labels.dtype == np.float32 and s.labels.shape == (len(s), n, 6)
    assert s.keys == tuple(t.key for t in ds.trajectories) and s.skipped == 0
    for ti, t in enumerate(ds.trajectories):
        rows = np.flatnonzero(s.trajectory == ti)
        assert s.start[rows].tolist() == starts  # every window of the trajectory, in order
        for row, first in zip(rows, starts):
            np.testing.assert_array_equal(s.frames[row], t.frame_index[first: first + n + 1])
            expected = [geometry.relative_pose(t.poses[first + k], t.poses[first + k + 1], frame) for k in range(n)]
            np.testing.assert_allclose(s.labels[row], np.array(expected), rtol=1e-6, atol=1e-4)
        for a, b in zip(rows, rows[1:]):  # consecutive windows share `overlap` pairs (and overlap+1 frames)
            np.testing.assert_array_equal(s.labels[b][:overlap], s.labels[a][n - overlap:])
            np.testing.assert_array_equal(s.frames[b][:overlap + 1], s.frames[a][n - overlap:])


def test_single_pairs_cover_every_pair_once_and_match_relative_labels(setup):
    ds, _ = setup
    s = windows(ds.trajectories, 1)
    assert len(s) == sum(t.n_pairs for t in ds.trajectories)
    assert len({(int(ti), int(st)) for ti, st in zip(s.trajectory, s.start)}) == len(s)
    for ti, t in enumerate(ds.trajectories):
        rows = s.trajectory == ti
        np.testing.assert_allclose(s.labels[rows][:, 0], relative_labels(t), atol=1e-4)
        np.testing.assert_array_equal(s.frames[rows], np.stack([t.frame_index[:-1], t.frame_index[1:]], 1))


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_relative_labels_accumulate_back_to_the_trajectory(setup, frame):
    ds, _ = setup
    t = ds.trajectories[0]  # crosses roll ±180°
    labels = relative_labels(t, frame)
    assert labels.shape == (FRAMES - 1, 6) and labels.dtype == np.float64
    acc = geometry.accumulate(t.poses[0], labels, frame)
    np.testing.assert_allclose(acc[:, :3], t.poses[:, :3], atol=1e-6)
    np.testing.assert_allclose(geometry.wrap_deg(acc[:, 3:] - t.poses[:, 3:]), 0, atol=1e-6)


def test_short_trajectories_are_skipped_and_counted(setup):
    ds, _ = setup
    trajs = [shortened(ds.trajectories[0], 4), *ds.trajectories[1:3], shortened(ds.trajectories[3], 6)]
    s = windows(trajs, 5)  # 3 pairs < 5: skipped; 5 pairs: exactly one window; 11 pairs: two
    assert s.skipped == 1
    assert s.keys == tuple(t.key for t in trajs)
    assert sorted(set(s.trajectory.tolist())) == [1, 2, 3]
    assert s.start[s.trajectory == 3].tolist() == [0] and s.start[s.trajectory == 1].tolist() == [0, 5]


def test_subset_and_evenly(setup):
    ds, _ = setup
    s = windows(ds.trajectories, 2)
    sub = s.subset([3, 0])
    np.testing.assert_array_equal(sub.frames, s.frames[[3, 0]])
    np.testing.assert_array_equal(sub.labels, s.labels[[3, 0]])
    assert sub.keys == s.keys and sub.trajectory.tolist() == s.trajectory[[3, 0]].tolist()
    assert s.evenly(None) is s and s.evenly(len(s) * 2) is s
    few = s.evenly(10)  # 10 pairs: 5 windows of 2, evenly spread, first and last kept
    assert len(few) == 5 and few.frames[0].tolist() == s.frames[0].tolist()
    assert few.frames[-1].tolist() == s.frames[-1].tolist()
    np.testing.assert_array_equal(s.evenly(10).frames, few.frames)  # the same every call


def test_bad_windows_are_clear_errors(setup):
    ds, _ = setup
    with pytest.raises(DataError, match=r"no trajectory has 21 frames .* \(longest: 12 frames\); lower data.window"):
        windows(ds.trajectories, 20)
    with pytest.raises(ConfigError, match=r"data.overlap: 4: must be .* smaller than the window \(4 pairs\)"):
        windows(ds.trajectories, 4, overlap=4)
    with pytest.raises(ConfigError, match=r"data.window: 0"):
        windows(ds.trajectories, 0)
    with pytest.raises(DataError, match=r"no trajectories"):
        windows([], 4)
    with pytest.raises(ValueError, match=r"pose frame 'body'"):
        relative_labels(ds.trajectories[0], "body")


# -- BatchOrder -----------------------------------------------------------------------------------


def test_each_epoch_is_a_shuffled_partition_in_full_batches():
    order = BatchOrder(n=23, batch=5, seed=3)
    assert order.per_epoch == 4  # 23 // 5: the incomplete rest is dropped
    epochs = []
    for epoch in range(3):
        batches = [order(epoch * 4 + k) for k in range(4)]
        assert all(len(b) == 5 and b.dtype.kind == "i" for b in batches)
        flat = np.concatenate(batches)
        assert len(set(flat.tolist())) == 20 and flat.min() >= 0 and flat.max() < 23
        assert [order.epoch_of(epoch * 4 + k) for k in range(4)] == [epoch] * 4
        epochs.append(flat)
    assert not np.array_equal(epochs[0], epochs[1]) and not np.array_equal(epochs[1], epochs[2])
    assert not np.array_equal(np.sort(epochs[0]), np.arange(20))  # shuffled, not the first 20 in order


def test_batch_i_depends_only_on_seed_and_i():
    a, b = BatchOrder(50, 8, seed=0), BatchOrder(50, 8, seed=0)
    sequence = [a(i).tolist() for i in range(20)]
    assert [b(i).tolist() for i in range(20)] == sequence
    resumed = BatchOrder(50, 8, seed=0)  # a resumed run starts at batch 13, then goes back and forth
    for i in (13, 14, 2, 19, 13, 0):
        assert resumed(i).tolist() == sequence[i]
    other = BatchOrder(50, 8, seed=1)
    assert [other(i).tolist() for i in range(20)] != sequence


def test_fewer_samples_than_a_batch_is_one_batch_per_epoch_and_none_is_an_error():
    order = BatchOrder(3, 8, seed=0)
    assert order.per_epoch == 1 and order.epoch_of(5) == 5
    assert sorted(order(0).tolist()) == [0, 1, 2] and sorted(order(1).tolist()) == [0, 1, 2]
    with pytest.raises(DataError, match="no training samples"):
        BatchOrder(0, 8, seed=0)


# -- FrameSource ----------------------------------------------------------------------------------


@pytest.mark.parametrize("resident", ["yes", "no", "auto"])
def test_frame_source_on_the_cpu_returns_the_frames_of_the_given_indices(setup, resident):
    ds, cache = setup
    source = FrameSource(cache, "cpu", resident=resident)
    assert source.resident == (resident == "yes")  # `yes` is honoured on any device: CI runs the resident path
    paths = ds.frames["path"].to_numpy()
    s = windows(ds.trajectories, 3, overlap=1)
    for idx in (s.frames[[4, 0, 9]], s.frames[:1], np.array([[7, 7], [30, 2]]), np.arange(10, 16)):
        out = source(idx)
        assert isinstance(out, torch.Tensor) and out.device.type == "cpu" and out.dtype == torch.uint8
        assert tuple(out.shape) == (*idx.shape, 3, 16, 16)
        expected = np.stack([png_frame(p) for p in paths[idx.reshape(-1)]]).reshape(*idx.shape, 3, 16, 16)
        np.testing.assert_array_equal(out.numpy(), expected)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("resident", ["yes", "no"])
def test_frame_source_on_cuda_gives_the_same_frames(setup, resident):
    ds, cache = setup
    source = FrameSource(cache, "cuda", resident=resident)
    assert source.resident == (resident == "yes")
    idx = windows(ds.trajectories, 3).frames[[5, 1]]
    out = source(idx)
    assert out.device.type == "cuda" and out.dtype == torch.uint8
    np.testing.assert_array_equal(out.cpu().numpy(), FrameSource(cache, "cpu")(idx).numpy())


# -- Photometric ----------------------------------------------------------------------------------


def frames_batch(setup) -> torch.Tensor:
    ds, cache = setup
    return FrameSource(cache)(windows(ds.trajectories, 3).frames[[0, 5, 9, 14]])  # [4, 4, 3, 16, 16]


def test_photometric_is_seeded_and_changes_pixels_not_shape(setup):
    x = frames_batch(setup)
    before = x.clone()
    aug = Photometric()
    a = aug(x, torch.Generator().manual_seed(1))
    b = aug(x, torch.Generator().manual_seed(1))
    c = aug(x, torch.Generator().manual_seed(2))
    torch.testing.assert_close(x, before)  # the input is untouched
    assert a.dtype == torch.uint8 and a.shape == x.shape and a.device == x.device
    torch.testing.assert_close(a, b)  # same generator state -> same pixels
    assert not torch.equal(a, x) and not torch.equal(a, c)
    assert (a.float() - x.float()).abs().mean() < 40  # a perturbation, not a new image


def test_photometric_draws_per_sample_and_shares_a_gain_over_its_frames(setup):
    x = frames_batch(setup)
    same = torch.stack([x[0], x[0]])  # two identical samples
    no_noise = Photometric(noise=0.0)
    out = no_noise(same, torch.Generator().manual_seed(0))
    assert not torch.equal(out[0], out[1])  # each sample draws its own brightness, contrast and gamma
    still = x[:1, :1].expand(1, 3, -1, -1, -1).contiguous()  # one sample, the same frame three times
    out = no_noise(still, torch.Generator().manual_seed(0))
    assert torch.equal(out[0, 0], out[0, 1]) and torch.equal(out[0, 1], out[0, 2])


def test_photometric_with_zero_strength_is_the_identity(setup):
    x = frames_batch(setup)
    off = Photometric(brightness=0.0, contrast=0.0, gamma=0.0, noise=0.0)
    torch.testing.assert_close(off(x, torch.Generator().manual_seed(0)), x)
