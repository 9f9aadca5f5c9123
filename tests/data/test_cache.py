"""The frame cache: decoded once, equal to the PNGs, keyed by fingerprint and size, safe to build twice at once."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image
from tinydata import write_tiny_dataset

from bronchocli.config import Splits
from bronchocli.data import cache as cache_mod
from bronchocli.data.cache import FrameCache, channel_stats
from bronchocli.data.reader import open_dataset_dir
from bronchocli.data.splits import make_split
from bronchocli.errors import DataError


@pytest.fixture
def ds(tmp_path):
    return open_dataset_dir(write_tiny_dataset(tmp_path / "ds", patients=2, lobes=("ur", "bl"), trajectories=3,
                                               frames=5, image_size=32))


@pytest.fixture
def decodes(monkeypatch):
    """Counts calls of the frame decoder."""
    calls = []
    real = cache_mod._decode

    def counting(path, shape):
        calls.append(path)
        return real(path, shape)

    monkeypatch.setattr(cache_mod, "_decode", counting)
    return calls


def png(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB")).transpose(2, 0, 1)


def test_built_once_and_equal_to_the_pngs(ds, tmp_path, decodes):
    cache = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    assert len(decodes) == ds.n_frames
    assert cache.shape == (ds.n_frames, 3, 32, 32) and cache.array.dtype == np.uint8
    for i, path in enumerate(ds.frames.path):
        np.testing.assert_array_equal(cache.array[i], png(path))
    again = FrameCache.open_or_build(ds, 32, tmp_path / "cache", progress=False)  # 32 = the dataset's size
    assert len(decodes) == ds.n_frames  # nothing decoded the second time
    assert again.path == cache.path
    assert sorted(p.suffix for p in (tmp_path / "cache").iterdir()) == [".json", ".lock", ".npy"]


def test_resized_cache_is_a_separate_antialiased_file(ds, tmp_path):
    full = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    half = FrameCache.open_or_build(ds, 16, tmp_path / "cache", progress=False)
    assert half.path != full.path and half.shape == (ds.n_frames, 3, 16, 16)
    blocks = full.array.astype(float).reshape(ds.n_frames, 3, 16, 2, 16, 2).mean((3, 5))
    assert np.abs(half.array.astype(float) - blocks).mean() < 2.0  # close to 2x2 averages (smooth images)


def test_changed_dataset_gets_a_new_cache(ds, tmp_path, decodes):
    first = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    ds.fingerprint = "0" * 64  # what a regenerated dataset looks like to the cache
    second = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    assert second.path != first.path and len(decodes) == 2 * ds.n_frames


def test_pickled_cache_reopens_lazily(ds, tmp_path):
    import pickle

    cache = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    _ = cache.array
    clone = pickle.loads(pickle.dumps(cache))
    assert clone._array is None and len(pickle.dumps(cache)) < 1000
    np.testing.assert_array_equal(clone.take([3, 4, 7]), cache.array[[3, 4, 7]])


def test_undecodable_frame_fails_without_leaving_a_cache(ds, tmp_path):
    bad = ds.frames.path.iat[7]
    with open(bad, "wb") as fh:
        fh.write(b"not a png")
    with pytest.raises(DataError, match=r"t\d+_f\d+\.png: cannot decode frame"):
        FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    assert not [p for p in (tmp_path / "cache").iterdir() if p.suffix != ".lock"]


def test_frame_of_another_size_needs_image_size(ds, tmp_path):
    Image.new("RGB", (40, 30)).save(ds.frames.path.iat[2])
    with pytest.raises(DataError, match=r"frame is 40x30 pixels, the dataset's are 32x32; set data.image_size"):
        FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    assert FrameCache.open_or_build(ds, 24, tmp_path / "cache", progress=False).shape[2:] == (24, 24)


_BUILDER = """
import sys
from bronchocli.data import cache as c
from bronchocli.data.reader import open_dataset_dir
calls = []
real = c._decode
c._decode = lambda p, s: calls.append(p) or real(p, s)
ds = open_dataset_dir(sys.argv[1])
print("ready", flush=True)
sys.stdin.readline()
cache = c.FrameCache.open_or_build(ds, None, sys.argv[2], progress=False)
print(len(calls), cache.path, int(cache.array.sum()))
"""


def test_two_processes_building_at_once_decode_once(ds, tmp_path):
    procs = [subprocess.Popen([sys.executable, "-c", _BUILDER, str(ds.root), str(tmp_path / "cache")],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True) for _ in range(2)]
    for p in procs:  # both have read the dataset ...
        assert p.stdout.readline().strip() == "ready"
    for p in procs:  # ... then both ask for the cache at the same moment
        p.stdin.write("go\n")
        p.stdin.flush()
    outs = [p.communicate(timeout=120)[0].split() for p in procs]
    assert all(p.returncode == 0 for p in procs)
    assert sorted(int(o[0]) for o in outs) == [0, ds.n_frames]  # one built, the other reused it
    assert outs[0][1:] == outs[1][1:]
    assert len(list((tmp_path / "cache").glob("*.npy"))) == 1 and not list((tmp_path / "cache").glob(".*tmp"))


def test_channel_stats_use_only_the_frames_given(ds, tmp_path):
    split = make_split(ds, "personalized", None, Splits(train=1, val=1, test=1))
    train = split.frame_indices("train")
    reference = np.stack([png(ds.frames.path.iat[i]) for i in train]).astype(float) / 255
    for i in np.concatenate([split.frame_indices("val"), split.frame_indices("test")]):
        Image.new("RGB", (32, 32)).save(ds.frames.path.iat[i])  # black val/test frames
    ds.fingerprint = "black-val-test"
    cache = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    mean, std = channel_stats(cache, train)
    np.testing.assert_allclose(mean, reference.mean((0, 2, 3)), atol=1e-12)
    np.testing.assert_allclose(std, reference.std((0, 2, 3)), atol=1e-12)
    assert mean.min() > 0.3  # not diluted by the black frames of the other splits
    all_mean, _ = channel_stats(cache, np.arange(ds.n_frames))
    assert np.all(all_mean < 0.5 * mean)
    sub_mean, _ = channel_stats(cache, train, max_frames=4)
    assert sub_mean.shape == (3,) and np.all(np.abs(sub_mean - mean) < 0.2)


def test_run_cache_follows_the_config(ds, tmp_path):
    from bronchocli.config import Config
    from bronchocli.data.cache import input_size, open_frame_cache

    cfg = Config(name="t", data={"image_size": 16, "cache_dir": str(tmp_path / "c")})
    cache = open_frame_cache(cfg, ds, progress=False)
    assert cache.shape == (ds.n_frames, 3, 16, 16) and cache.path.parent == tmp_path / "c"
    assert input_size(None, ds) == 32 and input_size(24, ds) == 24
    ds.frame_shape = (30, 40)
    with pytest.raises(DataError, match=r"frames are 40x30 \(not square\); set data.image_size"):
        input_size(None, ds)
