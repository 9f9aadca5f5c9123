"""The CSV importer reads foreign pose files (other column names, units, Euler conventions) correctly."""

from __future__ import annotations

import os

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation
from tinydata import write_tiny_dataset

from bronchocli.config import Config, CsvImport
from bronchocli.data.importer import import_csv
from bronchocli.data.reader import open_dataset_dir
from bronchocli.data.source import dataset_patients, open_dataset
from bronchocli.errors import DataError

SPACING = (0.5, 0.6, 0.7)
COLUMNS = {"patient": "Patient ID", "lobe": None, "trajectory": "Seq", "frame": "Idx", "x": "X", "y": "Y",
           "z": "Z", "rx": "Roll", "ry": "Pitch", "rz": "Yaw", "filename": "image"}


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    root = write_tiny_dataset(tmp_path_factory.mktemp("foreign") / "ds", patients=2, lobes=("ur", "bl"),
                              trajectories=3, frames=6, image_size=16)
    return root, open_dataset_dir(root)


def write_foreign(root, truth_ds, euler: str, units: str, positions: str, name: str = "poses.csv",
                  shuffle: bool = True) -> None:
    """Our ground truth rewritten as somebody else's CSV: one lobe-less sequence per (patient, lobe, traj)."""
    f = truth_ds.frames
    rot = Rotation.from_euler("XYZ", f[["rx", "ry", "rz"]].to_numpy(), degrees=True)
    angles = rot.as_euler(euler, degrees=units == "deg")
    pos = f[["x", "y", "z"]].to_numpy() * (np.asarray(SPACING) if positions == "mm" else 1.0)
    df = pd.DataFrame({
        "Patient ID": f.patient, "Seq": f.lobe + "-" + f.trajectory, "Idx": f.frame,
        "X": pos[:, 0], "Y": pos[:, 1], "Z": pos[:, 2], "Roll": angles[:, 0], "Pitch": angles[:, 1],
        "Yaw": angles[:, 2], "image": f.filename, "comment": "ignored",
    })
    if shuffle:
        df = df.sample(frac=1.0, random_state=0)
    df.to_csv(root / name, index=False)


def settings(euler: str, units: str, positions: str, **kw) -> CsvImport:
    kw = {"spacing_mm": SPACING, **kw}
    return CsvImport(files=["poses.csv"], columns=COLUMNS, angle_units=units, euler=euler,
                     position_units=positions, **kw)


@pytest.mark.parametrize("euler, units, positions", [
    ("ZYX", "rad", "mm"),  # intrinsic yaw-pitch-roll in radians, positions in mm
    ("xyz", "deg", "voxel"),  # extrinsic
    ("XYZ", "deg", "mm"),  # our convention, only the positions need converting
    ("zxz", "deg", "mm"),  # proper Euler angles
])
def test_foreign_csv_imports_to_the_same_poses(truth, euler, units, positions):
    root, ds = truth
    write_foreign(root, ds, euler, units, positions)
    imported = import_csv(root, settings(euler, units, positions))
    assert imported.patients == ds.patients and imported.lobes == ["all"]
    assert imported.n_frames == ds.n_frames and len(imported.trajectories) == len(ds.trajectories)
    assert imported.frame_shape == (16, 16)
    np.testing.assert_array_equal(imported.spacing_mm("p00"), SPACING)
    for t in ds.trajectories:
        got = imported.trajectory(f"{t.patient}/all/{t.lobe}-{t.traj_id}")
        np.testing.assert_allclose(got.poses[:, :3], t.poses[:, :3], atol=1e-9)
        r_got = Rotation.from_euler("XYZ", got.poses[:, 3:], degrees=True)
        r_gt = Rotation.from_euler("XYZ", t.poses[:, 3:], degrees=True)
        assert np.degrees((r_got.inv() * r_gt).magnitude()).max() < 1e-6
        assert got.filenames == t.filenames


def test_frame_order_and_patient_from_the_file(truth, tmp_path):
    root, ds = truth
    one = ds.frames[ds.frames.patient == "p01"]
    rows = one.rename(columns={"x": "px", "y": "py", "z": "pz"})[["lobe", "trajectory", "px", "py", "pz",
                                                                  "rx", "ry", "rz", "filename"]]
    (tmp_path / "frames").symlink_to(root, target_is_directory=True)
    rows.to_csv(tmp_path / "Case 7.csv", index=False)
    cfg = CsvImport(frames="frames", columns=dict(patient=None, frame=None, x="px", y="py", z="pz"))
    imported = import_csv(tmp_path, cfg)
    assert imported.patients == ["Case_7"]  # file stem, made a safe id
    t = ds.trajectory("p01/bl/2")
    got = imported.trajectory("Case_7/bl/2")
    np.testing.assert_array_equal(got.poses, t.poses)  # XYZ degrees voxels: copied as they are
    np.testing.assert_array_equal(got.frame_index - got.frame_index[0], np.arange(t.n_frames))


def test_missing_column_names_the_config_key(truth):
    root, ds = truth
    write_foreign(root, ds, "ZYX", "deg", "mm")
    cfg = CsvImport(files=["poses.csv"], columns={**COLUMNS, "rz": "Heading"})
    with pytest.raises(DataError, match=r"poses.csv: missing column\(s\) 'Heading' \(dataset.csv.columns.rz\)"):
        import_csv(root, cfg)


def test_non_numeric_pose_names_the_line_and_column(truth, tmp_path):
    _, ds = truth
    write_foreign(tmp_path, ds, "ZYX", "deg", "mm", shuffle=False)
    df = pd.read_csv(tmp_path / "poses.csv")
    df["Pitch"] = df["Pitch"].astype(object)
    df.loc[4, "Pitch"] = "abc"
    df.to_csv(tmp_path / "poses.csv", index=False)
    with pytest.raises(DataError, match=r"poses.csv line 6: .*column 'Pitch': 'abc'"):
        import_csv(tmp_path, settings("ZYX", "deg", "mm"))


def test_missing_frame_and_unmatched_glob_are_errors(truth, tmp_path):
    _, ds = truth
    write_foreign(tmp_path, ds, "XYZ", "deg", "voxel", shuffle=False)
    with pytest.raises(DataError, match=r"poses.csv line 2: frame file 'p00/ur/t000_f0000.png' not found"):
        import_csv(tmp_path, settings("XYZ", "deg", "voxel"))
    with pytest.raises(DataError, match=r"dataset.csv.files: 'nothing\*.csv' matches no file"):
        import_csv(tmp_path, CsvImport(files=["nothing*.csv"]))


def test_fingerprint_follows_csv_settings_and_frames(truth):
    root, ds = truth
    write_foreign(root, ds, "ZYX", "deg", "mm", shuffle=False)
    base = import_csv(root, settings("ZYX", "deg", "mm")).fingerprint
    assert import_csv(root, settings("ZYX", "deg", "mm")).fingerprint == base
    assert import_csv(root, settings("ZYX", "deg", "mm", spacing_mm=(1, 1, 1))).fingerprint != base
    frame = root / ds.frames.filename.iat[3]
    st = frame.stat()
    os.utime(frame, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert import_csv(root, settings("ZYX", "deg", "mm")).fingerprint != base


def test_config_dispatch_and_patient_ids(truth):
    root, ds = truth
    write_foreign(root, ds, "ZYX", "rad", "mm")
    cfg = Config(name="t", dataset={"root": str(root), "format": "csv",
                                    "csv": settings("ZYX", "rad", "mm").model_dump()})
    assert open_dataset(cfg).format == "csv"
    assert dataset_patients(cfg) == ["p00", "p01"]
