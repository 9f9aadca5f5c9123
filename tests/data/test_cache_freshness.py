"""The frame cache notices frames rewritten after it was built (same name, new pixels) and rebuilds itself."""

from __future__ import annotations

import logging
import os

import numpy as np
import pytest
from PIL import Image
from tinydata import write_tiny_dataset

from bronchocli.data.cache import FrameCache
from bronchocli.data.reader import open_dataset_dir
from bronchocli.errors import DataError


@pytest.fixture
def ds(tmp_path):
    return open_dataset_dir(write_tiny_dataset(tmp_path / "ds", patients=1, lobes=("ur",), trajectories=2, frames=4,
                                               image_size=16))


def rewrite(path: str, colour: tuple[int, int, int]) -> np.ndarray:
    """Replace a frame by a solid colour; returns the new pixels as the cache stores them (3, H, W)."""
    pixels = np.zeros((16, 16, 3), np.uint8) + np.array(colour, np.uint8)
    Image.fromarray(pixels).save(path)
    return pixels.transpose(2, 0, 1)


def test_a_frame_rewritten_after_the_build_is_read_anew(ds, tmp_path, caplog):
    cache = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    target = ds.frames["path"].iat[5]
    before = np.array(cache.array[5])
    new = rewrite(target, (200, 10, 30))
    assert not np.array_equal(before, new)
    with caplog.at_level(logging.WARNING, logger="bronchocli.data.cache"):
        again = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    np.testing.assert_array_equal(again.array[5], new)
    np.testing.assert_array_equal(again.array[4], cache.array[4])
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and target in warnings[0] and "rebuilding" in warnings[0]


def test_same_size_but_a_new_mtime_also_counts_as_changed(ds, tmp_path):
    target = ds.frames["path"].iat[2]
    rewrite(target, (1, 2, 3))
    first = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    assert (first.array[2] == np.array([1, 2, 3])[:, None, None]).all()
    st = os.stat(target)
    new = rewrite(target, (3, 2, 1))  # same size, other pixels, and (as a later rewrite would) a newer mtime
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert os.path.getsize(target) == st.st_size
    fresh = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    np.testing.assert_array_equal(fresh.array[2], new)


def test_an_unchanged_dataset_reuses_the_cache_and_a_vanished_frame_is_one_clear_error(ds, tmp_path):
    first = FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    built = first.path.stat().st_mtime_ns
    assert FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False).path.stat().st_mtime_ns == built
    gone = ds.frames["path"].iat[3]
    os.remove(gone)
    with pytest.raises(DataError, match="cannot decode frame") as info:
        FrameCache.open_or_build(ds, None, tmp_path / "cache", progress=False)
    assert gone in str(info.value) and "\n" not in str(info.value)
