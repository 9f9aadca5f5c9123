"""The data layer says what degraded: an empty lobe, CSVs edited after generation (and the fingerprint then
follows the real contents), frames converted to RGB or resized."""

from __future__ import annotations

import hashlib
import json
import logging
import os

import numpy as np
import pandas as pd
import pytest
from PIL import Image
from tinydata import write_tiny_dataset

from bronchocli.data import reader
from bronchocli.data.cache import FrameCache
from bronchocli.data.reader import open_dataset_dir


@pytest.fixture
def ds_root(tmp_path, monkeypatch):
    monkeypatch.setattr(reader, "_warned", set())
    return write_tiny_dataset(tmp_path / "ds", patients=2, lobes=("ur", "bl"), trajectories=2, frames=4,
                              image_size=32)


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def _drop_lobe(root, patient: str, lobe: str) -> None:
    csv = root / f"{patient}.csv"
    table = pd.read_csv(csv, dtype=str)
    table[table["lobe"] != lobe].to_csv(csv, index=False)


def test_an_emptied_lobe_is_a_warning_and_changes_the_fingerprint(ds_root, caplog):
    before = open_dataset_dir(ds_root).fingerprint
    assert not _warnings(caplog)
    written = (ds_root / "dataset.json").stat().st_mtime_ns
    os.utime(ds_root / "dataset.json", ns=(written - 60 * 10**9,) * 2)  # generated a minute before the edit
    _drop_lobe(ds_root, "p01", "bl")
    with caplog.at_level(logging.WARNING):
        after = open_dataset_dir(ds_root)
    text = " ".join(_warnings(caplog))
    assert "no trajectories in p01/bl" in text and "p01.csv changed after dataset.json" in text, text
    assert after.fingerprint != before and len(after.fingerprint) == 64


def test_recorded_csv_hashes_catch_an_edit_whatever_the_file_times(ds_root, caplog):
    meta = json.loads((ds_root / "dataset.json").read_text())
    meta["csv_sha256"] = {p: hashlib.sha256((ds_root / f"{p}.csv").read_bytes()).hexdigest() for p in meta["patients"]}
    (ds_root / "dataset.json").write_text(json.dumps(meta))
    assert open_dataset_dir(ds_root).fingerprint == meta["fingerprint"]  # untouched: the generator's fingerprint
    _drop_lobe(ds_root, "p00", "ur")
    os.utime(ds_root / "dataset.json")  # dataset.json looks newer than the edit: the hashes still tell
    with caplog.at_level(logging.WARNING):
        edited = open_dataset_dir(ds_root)
    assert edited.fingerprint != meta["fingerprint"]
    assert "no trajectories in p00/ur" in " ".join(_warnings(caplog))


def _frames(root):
    return sorted(root.rglob("*.png"))


def test_grayscale_frames_are_converted_with_a_warning(ds_root, tmp_path, caplog):
    frame = _frames(ds_root)[0]
    Image.open(frame).convert("L").save(frame)
    with caplog.at_level(logging.WARNING):
        cache = FrameCache.open_or_build(open_dataset_dir(ds_root), None, tmp_path / "cache", progress=False)
    text = " ".join(_warnings(caplog))
    assert "1 frame(s) were not RGB (mode L" in text and frame.name in text, text
    assert cache.array.shape[1] == 3


def test_frames_of_another_size_are_resized_with_a_warning(ds_root, tmp_path, caplog):
    frame = _frames(ds_root)[1]
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(frame)
    with caplog.at_level(logging.WARNING):
        FrameCache.open_or_build(open_dataset_dir(ds_root), 32, tmp_path / "cache", progress=False)
    text = " ".join(_warnings(caplog))
    assert "1 frame(s) were not the dataset's 32x32 pixels" in text and "is 16x16" in text, text


def test_a_clean_dataset_says_nothing(ds_root, tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        FrameCache.open_or_build(open_dataset_dir(ds_root), 32, tmp_path / "cache", progress=False)
    assert not _warnings(caplog)
