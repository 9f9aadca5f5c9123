"""track's inputs: folders in natural order, dataset trajectories by key, videos, ground-truth CSVs, bad inputs."""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd
import pytest
from PIL import Image
from tinydata import write_tiny_dataset

from bronchocli.errors import BronchoError, DataError
from bronchocli.inference import reader


def _frame(value: int, size=(16, 16)) -> Image.Image:
    return Image.fromarray(np.full((size[1], size[0], 3), value, np.uint8))


def test_a_folder_is_read_in_natural_name_order(tmp_path):
    for i in (10, 2, 1):
        _frame(i).save(tmp_path / f"f{i}.png")
    (tmp_path / "notes.txt").write_text("not a frame")
    inp = reader.open_input(tmp_path)
    assert inp.labels == ("f1.png", "f2.png", "f10.png") and inp.shape == (16, 16) and inp.n_frames == 3
    assert [int(f[0, 0, 0]) for f in inp.frames()] == [1, 2, 10]


def test_a_dataset_trajectory_by_key_brings_its_poses_and_spacing(tmp_path, monkeypatch):
    root = write_tiny_dataset(tmp_path / "ds", patients=1, lobes=("ur",), trajectories=2, frames=5, image_size=16)
    inp = reader.open_input(root / "p00" / "ur" / "1")
    table = pd.read_csv(root / "p00.csv")
    rows = table[table.trajectory == 1].sort_values("frame")
    np.testing.assert_array_equal(inp.ground_truth.poses, rows[list(reader.DISK_POSE_COLUMNS)].to_numpy(float))
    np.testing.assert_array_equal(inp.ground_truth.spacing_mm, [0.5, 0.5, 0.5])
    assert inp.kind == "trajectory" and inp.ground_truth.key == "p00/ur/1" and len(list(inp.frames())) == 5
    monkeypatch.chdir(root)  # relative to the dataset root itself
    assert reader.open_input("p00/ur/0").ground_truth.key == "p00/ur/0"
    with pytest.raises(DataError, match="no trajectory 'p00/ur/7'"):
        reader.open_input(root / "p00" / "ur" / "7")


def test_ground_truth_from_tracks_own_csv_is_sorted_by_frame(tmp_path):
    poses = np.arange(18, dtype=float).reshape(3, 6)
    table = pd.DataFrame(poses, columns=list(reader.DISK_POSE_COLUMNS))
    table.insert(0, "frame", [0, 1, 2])
    table.iloc[::-1].to_csv(tmp_path / "gt.csv", index=False)
    truth = reader.read_ground_truth(tmp_path / "gt.csv")
    np.testing.assert_array_equal(truth.poses, poses)
    assert np.isnan(truth.spacing_mm).all()
    pd.DataFrame({"a": [1]}).to_csv(tmp_path / "bad.csv", index=False)
    with pytest.raises(DataError, match="needs the pose columns pos_x pos_y pos_z Rx Ry Rz"):
        reader.read_ground_truth(tmp_path / "bad.csv")


def test_one_frame_is_not_a_trajectory(tmp_path):
    _frame(1).save(tmp_path / "a.png")
    with pytest.raises(DataError, match="1 frame\\(s\\); tracking needs at least 2"):
        reader.open_input(tmp_path)


def test_a_video_without_pyav_names_the_extra(tmp_path, monkeypatch):
    (tmp_path / "clip.mp4").write_bytes(b"\0" * 64)
    monkeypatch.setitem(sys.modules, "av", None)
    with pytest.raises(BronchoError, match=r"pip install 'bronchocli\[video\]'"):
        reader.open_input(tmp_path / "clip.mp4")
