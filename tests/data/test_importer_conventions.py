"""Imported camera conventions (z-forward, y-down cameras) and poses-only CSVs (no frames, no trajectory column)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.spatial.transform import Rotation

from bronchocli import geometry
from bronchocli.config import CsvImport, load_config
from bronchocli.data.cache import open_frame_cache
from bronchocli.data.importer import import_csv
from bronchocli.errors import ConfigError, DataError

# An OpenCV-style camera: z is the optical axis, x points right, y points down. In our camera (x forward,
# y left, z up) its axes are: our x = its z, our y = -(its x), our z = -(its y). P's columns are our axes in its frame.
P = np.array([[0.0, -1.0, 0.0],
              [0.0, 0.0, -1.0],
              [1.0, 0.0, 0.0]])


def opencv_trajectory(n: int = 40, seed: int = 0) -> tuple[np.ndarray, Rotation]:
    """A camera flying mostly along its own optical axis (+z) while turning: world positions and orientations."""
    rng = np.random.default_rng(seed)
    rot = [Rotation.from_euler("ZYX", [30, -20, 10], degrees=True)]
    pos = [np.array([50.0, 40.0, 60.0])]
    for _ in range(n - 1):
        step = rot[-1].apply([rng.normal(0, 0.05), rng.normal(0, 0.05), 1.0])  # forward in the camera's own frame
        pos.append(pos[-1] + step)
        rot.append(rot[-1] * Rotation.from_rotvec(rng.normal(0, 0.05, 3)))
    return np.array(pos), Rotation.concatenate(rot)


def write_csv(path, pos: np.ndarray, rot: Rotation, euler: str = "ZYX", **extra) -> None:
    angles = rot.as_euler(euler, degrees=True)
    pd.DataFrame({"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2], "a": angles[:, 0], "b": angles[:, 1],
                  "c": angles[:, 2], **extra}).to_csv(path, index=False)


POSES_ONLY = {"patient": None, "lobe": None, "trajectory": None, "frame": None, "filename": None,
              "rx": "a", "ry": "b", "rz": "c"}


def test_z_forward_y_down_camera_gives_our_relative_poses(tmp_path):
    pos, rot = opencv_trajectory()
    write_csv(tmp_path / "cam.csv", pos, rot)
    cfg = CsvImport(euler="ZYX", columns=POSES_ONLY, camera_forward="z", camera_up="-y")
    (traj,) = import_csv(tmp_path, cfg).trajectories
    np.testing.assert_allclose(traj.poses[:, :3], pos, atol=1e-9)  # positions are untouched
    # The optical axis (DE's look-at vector, R·(1,0,0) in our convention) is the camera's own z axis.
    np.testing.assert_allclose(geometry.forward_vector(traj.poses[:, 3:]), rot.apply([0, 0, 1]), atol=1e-9)
    rel = geometry.relative_trajectory(traj.poses, "camera")
    # Expected from SciPy alone: the motion in the previous OpenCV camera's frame, then re-expressed in ours.
    dp_cv = rot[:-1].inv().apply(pos[1:] - pos[:-1])
    np.testing.assert_allclose(rel[:, :3], dp_cv @ P, atol=1e-9)  # (z, -x, -y) of the OpenCV motion
    assert (rel[:, 0] > 0.9).all()  # flying forward is +x in our camera frame
    dr_cv = rot[:-1].inv() * rot[1:]
    expected = Rotation.from_matrix(P.T @ dr_cv.as_matrix() @ P)
    got = Rotation.from_euler("XYZ", rel[:, 3:], degrees=True)
    assert np.degrees((got.inv() * expected).magnitude()).max() < 1e-6


def test_default_axes_leave_x_forward_data_as_it_is(tmp_path):
    pos, rot = opencv_trajectory(n=5)
    write_csv(tmp_path / "cam.csv", pos, rot, euler="XYZ")
    (traj,) = import_csv(tmp_path, CsvImport(euler="XYZ", columns=POSES_ONLY)).trajectories
    np.testing.assert_allclose(traj.poses[:, 3:], rot.as_euler("XYZ", degrees=True), atol=1e-9)


def test_camera_axes_must_differ():
    with pytest.raises(ValueError, match="must be different axes"):
        CsvImport(camera_forward="z", camera_up="-z")


def poses_only_project(tmp_path, trajectories: bool) -> str:
    rows = []
    for patient in ("p0", "p1"):
        for t in range(6 if trajectories else 1):
            pos, rot = opencv_trajectory(n=5, seed=t + (10 if patient == "p1" else 0))
            angles = rot.as_euler("XYZ", degrees=True)
            for k in range(5):
                rows.append({"patient": patient, "trajectory": t, "x": pos[k, 0], "y": pos[k, 1], "z": pos[k, 2],
                             "a": angles[k, 0], "b": angles[k, 1], "c": angles[k, 2]})
    (tmp_path / "data").mkdir()
    pd.DataFrame(rows).to_csv(tmp_path / "data" / "poses.csv", index=False)
    columns = {**POSES_ONLY, "patient": "patient", "trajectory": "trajectory" if trajectories else None}
    config = {"name": "poses", "dataset": {"root": "data", "format": "csv", "csv": {"columns": columns}},
              "splits": {"train": 4, "val": 1, "test": 1}, "runs": {"uri": "sqlite:///runs/mlflow.db"}}
    (tmp_path / "experiments.yaml").write_text(yaml.safe_dump(config))
    return str(tmp_path / "experiments.yaml")


def test_a_poses_only_dataset_reads_splits_and_shows_stats(cli, tmp_path):
    path = poses_only_project(tmp_path, trajectories=True)
    code, out, err = cli("data", "stats", "-c", path, "--population", "personalized")
    assert code == 0, err
    assert "none (poses only)" in out and "p0" in out and "p1" in out
    assert "Traceback" not in out + err


def test_one_trajectory_per_patient_when_there_is_no_trajectory_column(tmp_path):
    poses_only_project(tmp_path, trajectories=False)
    cfg = CsvImport(columns={**POSES_ONLY, "patient": "patient"})
    ds = import_csv(tmp_path / "data", cfg)
    assert [t.key for t in ds.trajectories] == ["p0/all/0", "p1/all/0"] and ds.n_frames == 10
    assert not ds.has_frames


def test_training_on_a_poses_only_dataset_is_one_clear_error(cli, tmp_path):
    path = poses_only_project(tmp_path, trajectories=True)
    code, out, err = cli("train", "-c", path, "-a", "baseline", "-l", "mse", "-P", "personalized", "-q")
    assert code == 2, out + err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "poses-only dataset" in lines[0] and "dataset.csv.columns.filename" in lines[0]


def test_the_frame_cache_refuses_a_poses_only_dataset(tmp_path):
    cfg = load_config(poses_only_project(tmp_path, trajectories=False))
    ds = import_csv(cfg.paths.dataset, cfg.dataset.csv)
    with pytest.raises(DataError, match="no frames to train on"):
        open_frame_cache(cfg, ds, progress=False)


def test_bad_camera_axis_in_the_config_names_the_key(tmp_path):
    (tmp_path / "e.yaml").write_text("name: t\ndataset:\n  csv:\n    camera_forward: w\n")
    with pytest.raises(ConfigError, match=r"e.yaml:4: dataset.csv.camera_forward"):
        load_config(tmp_path / "e.yaml")
