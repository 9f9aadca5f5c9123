"""World-frame labels near gimbal lock: a trajectory whose Euler differences are far larger than its rotation
between frames is named, with its frames, at import, by `data stats` and by world-frame training."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation
from tinydata import turning_angles as turning

from bronchocli.config import CsvImport
from bronchocli.data import gimbal, reader
from bronchocli.data.importer import import_csv
from bronchocli.data.stats import gimbal_table

COLUMNS = {"patient": None, "lobe": None, "frame": None, "filename": None, "trajectory": "traj",
           "rx": "a", "ry": "b", "rz": "c"}


@pytest.fixture
def through_lock(tmp_path, monkeypatch):
    monkeypatch.setattr(reader, "_warned", set())
    rows = []
    for name, beta in (("calm", -40.0), ("lock", -88.9)):
        angles = turning(beta)
        rows.append(pd.DataFrame({"traj": name, "x": np.arange(40.0), "y": 0.0, "z": 0.0,
                                  "a": angles[:, 0], "b": angles[:, 1], "c": angles[:, 2]}))
    pd.concat(rows).to_csv(tmp_path / "p0.csv", index=False)
    return tmp_path


def test_import_through_gimbal_lock_names_the_trajectory_and_its_frames(through_lock, caplog):
    with caplog.at_level(logging.WARNING):
        ds = import_csv(through_lock, CsvImport(euler="XYZ", columns=COLUMNS))
    warnings = [r.getMessage() for r in caplog.records if "gimbal lock" in r.getMessage()]
    assert len(warnings) == 1, warnings
    text = warnings[0]
    assert "world-frame labels near gimbal lock in 1 of 2 trajectories: p0/all/lock frames " in text
    assert "calm" not in text and "camera-frame labels are unaffected" in text
    (jumps,) = gimbal.world_label_jumps(ds)
    lock = next(t for t in ds.trajectories if t.traj_id == "lock")
    euler, true = gimbal.pair_angles(lock.poses)
    assert jumps.euler_max > 20.0 > 5.0 > jumps.rotation_max == pytest.approx(true.max(), abs=0.1)
    assert f"frames {gimbal.frame_ranges(jumps.frames)} " in text
    # the named frames are exactly the pairs whose Euler difference jumps: an independent count from SciPy
    R = Rotation.from_euler("XYZ", lock.poses[:, 3:], degrees=True)
    geodesic = np.degrees((R[:-1].inv() * R[1:]).magnitude())
    diffs = np.linalg.norm((np.diff(lock.poses[:, 3:], axis=0) + 180.0) % 360.0 - 180.0, axis=1)
    assert list(jumps.frames) == [i + 1 for i in np.flatnonzero((diffs - geodesic > 10) & (diffs > 2 * geodesic))]
    table = gimbal_table(ds)
    assert table["trajectory"].tolist() == ["p0/all/lock"] and table["pairs"].iat[0] == len(jumps.frames)


def test_no_warning_away_from_gimbal_lock(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(reader, "_warned", set())
    angles = turning(-60.0)
    pd.DataFrame({"traj": "t", "x": np.arange(40.0), "y": 0.0, "z": 0.0, "a": angles[:, 0], "b": angles[:, 1],
                  "c": angles[:, 2]}).to_csv(tmp_path / "p0.csv", index=False)
    with caplog.at_level(logging.WARNING):
        ds = import_csv(tmp_path, CsvImport(euler="XYZ", columns=COLUMNS))
    assert not [r for r in caplog.records if "gimbal" in r.getMessage()]
    assert gimbal.world_label_warning(ds) == "" and gimbal_table(ds).empty


def test_frame_ranges():
    assert gimbal.frame_ranges([9, 3, 4, 5]) == "3-5, 9"
    assert gimbal.frame_ranges([]) == ""
