"""The dataset reader: what it reads, the pose round trip in both frames, and each validation error."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation
from tinydata import write_tiny_dataset

from bronchocli import geometry
from bronchocli.config import Config
from bronchocli.data.batches import relative_labels
from bronchocli.data.reader import open_dataset_dir
from bronchocli.data.source import open_dataset
from bronchocli.errors import DataError


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("tiny") / "ds")


@pytest.fixture
def small(tmp_path):
    """A small dataset of our own that a test may break."""
    return write_tiny_dataset(tmp_path / "ds", patients=2, lobes=("ur", "bl"), trajectories=2, frames=4, image_size=16)


def disk_table(root) -> pd.DataFrame:
    meta = json.loads((root / "dataset.json").read_text())
    return pd.concat([pd.read_csv(root / f"{p}.csv") for p in meta["patients"]], ignore_index=True)


def test_reads_every_frame_and_trajectory_as_on_disk(tiny):
    ds = open_dataset_dir(tiny)
    meta = json.loads((tiny / "dataset.json").read_text())
    disk = disk_table(tiny)
    assert ds.patients == ["p00", "p01", "p02"] and ds.lobes == ["ur", "br", "ul", "bl"]
    assert ds.n_frames == meta["counts"]["frames"] == len(disk)
    assert len(ds.trajectories) == meta["counts"]["trajectories"] == 72
    assert ds.image_size == 32 and ds.frame_shape == (32, 32) and ds.fingerprint == meta["fingerprint"]
    np.testing.assert_array_equal(ds.spacing_mm("p01"), [0.5, 0.5, 0.5])
    assert list(ds.frames.index) == list(range(ds.n_frames))
    for t in ds.trajectories:
        rows = disk[(disk.patient == t.patient) & (disk.lobe == t.lobe) & (disk.trajectory == int(t.traj_id))]
        rows = rows.sort_values("frame")
        np.testing.assert_array_equal(t.poses, rows[["pos_x", "pos_y", "pos_z", "Rx", "Ry", "Rz"]].to_numpy())
        assert [str(tiny / f) for f in rows.filename] == list(t.filenames)
        assert list(ds.frames.loc[t.frame_index, "filename"]) == list(rows.filename)
        assert t.key == f"{t.patient}/{t.lobe}/{t.traj_id}"


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_labels_accumulate_back_to_the_poses_on_disk(tiny, frame):
    ds = open_dataset_dir(tiny)
    disk = disk_table(tiny)
    crossed = 0
    for t in ds.trajectories:
        rows = disk[(disk.patient == t.patient) & (disk.lobe == t.lobe) & (disk.trajectory == int(t.traj_id))]
        truth = rows.sort_values("frame")[["pos_x", "pos_y", "pos_z", "Rx", "Ry", "Rz"]].to_numpy()
        labels = relative_labels(t, frame)
        assert labels.shape == (len(truth) - 1, 6)
        assert np.all(labels[:, 3:] > -180) and np.all(labels[:, 3:] <= 180)
        crossed += int(np.any(np.abs(np.diff(truth[:, 3:], axis=0)) > 180))
        acc = geometry.accumulate(truth[0], labels, frame)
        np.testing.assert_allclose(acc[:, :3], truth[:, :3], atol=1e-9)
        r_acc = Rotation.from_euler("XYZ", acc[:, 3:], degrees=True)
        r_gt = Rotation.from_euler("XYZ", truth[:, 3:], degrees=True)
        assert np.degrees((r_acc.inv() * r_gt).magnitude()).max() < 1e-7
        if frame == "world":
            np.testing.assert_allclose(geometry.wrap_deg(acc[:, 3:] - truth[:, 3:]), 0, atol=1e-9)
    assert crossed >= 12  # the ±180° wrap was exercised


def test_open_dataset_follows_the_config(tiny, tmp_path):
    cfg = Config(name="t", dataset={"root": str(tiny)})
    assert open_dataset(cfg).fingerprint == open_dataset_dir(tiny).fingerprint


def _edit_csv(root, patient, fn):
    path = root / f"{patient}.csv"
    df = fn(pd.read_csv(path))
    df.to_csv(path, index=False)


def _drop_column(root):
    _edit_csv(root, "p01", lambda df: df.drop(columns=["Rz"]))


def _remove_frame(root):
    (root / "p01/bl/t001_f0002.png").unlink()


def _nan_pose(root):
    def edit(df):
        df.loc[5, "Ry"] = np.nan
        return df
    _edit_csv(root, "p00", edit)


def _short_trajectory(root):
    _edit_csv(root, "p01", lambda df: df[~((df.lobe == "ur") & (df.trajectory == 1) & (df.frame > 0))])


def _duplicate_frame(root):
    _edit_csv(root, "p00", lambda df: pd.concat([df, df.iloc[[3]]], ignore_index=True))


def _bad_frame_number(root):
    def edit(df):
        df["frame"] = df["frame"].astype(object)
        df.loc[2, "frame"] = "two"
        return df
    _edit_csv(root, "p00", edit)


@pytest.mark.parametrize("breaker, expected", [
    (_drop_column, ["p01.csv", "missing column", "Rz"]),
    (_remove_frame, ["p01.csv line 16", "p01/bl/t001_f0002.png", "not found"]),
    (_nan_pose, ["p00.csv line 7", "non-finite", "ry=nan"]),
    (_short_trajectory, ["p01.csv line 6", "p01/ur/1", "has 1 frame"]),
    (_duplicate_frame, ["p00.csv line", "frame 3 appears twice", "p00/ur/0"]),
    (_bad_frame_number, ["p00.csv line 4", "whole number", "two"]),
    (lambda root: _edit_csv(root, "p01", lambda df: df.iloc[:0]), ["p01.csv: no frames"]),
    (lambda root: (root / "p00.csv").write_bytes(b""), ["p00.csv: not a readable CSV"]),
    (lambda root: (root / "dataset.json").unlink(), ["dataset.json: not found"]),
    (lambda root: (root / "p01.csv").unlink(), ["p01.csv: not found", "p01"]),
    (lambda root: shutil.rmtree(root), ["dataset directory not found"]),
])
def test_each_problem_is_one_clear_error_naming_file_and_line(small, breaker, expected):
    breaker(small)
    with pytest.raises(DataError) as err:
        open_dataset_dir(small)
    message = str(err.value)
    assert "\n" not in message
    for text in expected:
        assert text in message


def test_bad_dataset_json_is_reported(small):
    meta = json.loads((small / "dataset.json").read_text())
    del meta["voxel_grid"]["p01"]
    (small / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"dataset.json: voxel_grid.p01.spacing_mm"):
        open_dataset_dir(small)


# -- issue 37.4/37.5: absurd poses, names that leave the dataset, symlink loops ---------------------------------

def _set_pose(column: str, value: float, row: int = 5):
    def breaker(root):
        def edit(df):
            df[column] = df[column].astype(np.float64)
            df.loc[row, column] = value
            return df
        _edit_csv(root, "p00", edit)
    return breaker


@pytest.mark.parametrize("column, value, expected", [
    ("pos_x", 1e308, ["p00.csv line 7", "out-of-range pose value x=1e+308", "±1,000,000 voxels"]),
    ("pos_z", -1.5e6, ["p00.csv line 7", "z=-1.5e+06", "positions within ±1,000,000 voxels"]),
    ("Rx", 721.0, ["p00.csv line 7", "rx=721", "angles within ±720°"]),
    ("Rz", -1e9, ["p00.csv line 7", "rz=-1e+09", "angles within ±720°"]),
    ("Ry", np.inf, ["p00.csv line 7", "non-finite pose value ry=inf"]),
])
def test_absurd_pose_values_are_one_line_naming_file_line_and_value(small, column, value, expected):
    _set_pose(column, value)(small)
    with pytest.raises(DataError) as err:
        open_dataset_dir(small)
    message = str(err.value)
    assert "\n" not in message and all(text in message for text in expected), message


def test_poses_at_the_bounds_are_read(small):
    _set_pose("pos_y", -1e6, row=2)(small)
    _set_pose("Rz", 720.0, row=3)(small)
    ds = open_dataset_dir(small)
    assert ds.frames["y"].min() == -1e6  # an extreme but finite position is data, not corruption


@pytest.mark.parametrize("name", ["../..", "..", "a/b", ""])
def test_a_lobe_of_dataset_json_that_is_not_a_plain_name_is_refused(small, name):
    meta = json.loads((small / "dataset.json").read_text())
    meta["lobes"] = ["ur", name]
    (small / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"dataset.json: lobes\[1\] .*: a lobe name is a folder name"):
        open_dataset_dir(small)


@pytest.mark.parametrize("column, value", [("lobe", "../x"), ("trajectory", "a/b")])
def test_a_lobe_or_trajectory_of_a_row_that_leaves_its_folder_is_refused(small, column, value):
    def edit(df):
        df[column] = df[column].astype(object)
        df.loc[4, column] = value
        return df
    _edit_csv(small, "p00", edit)
    with pytest.raises(DataError, match=rf"p00.csv line 6: {column} '{value}': a {column} is a folder name"):
        open_dataset_dir(small)


@pytest.mark.parametrize("name", ["dataset.json", "p00.csv"])
def test_a_symlink_loop_in_a_dataset_file_is_named_a_loop_not_missing(small, name):
    from bronchocli.errors import BronchoError

    (small / name).unlink()
    (small / name).symlink_to(small / name)
    with pytest.raises(BronchoError) as err:
        open_dataset_dir(small)
    assert "symbolic link loop" in str(err.value) and name in str(err.value) and "not found" not in str(err.value)
