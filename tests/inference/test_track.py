"""`bronchopose track`: a run's model on a dataset trajectory, a folder of frames or a video; errors as logged."""

from __future__ import annotations

import shutil
from pathlib import Path

import av
import numpy as np
import pandas as pd
import pytest
from PIL import Image

from bronchocli import geometry
from bronchocli.data.reader import DISK_POSE_COLUMNS
from bronchocli.runs.client import client_for, experiment_id


def columns(errors: pd.DataFrame, source: str) -> list[str]:
    """Every error column of one source: <source>.pair.*, <source>.acc.* and <source>.traj.* (CTF, ATE, RPE...)."""
    return [c for c in errors.columns if c.startswith(f"{source}.")]


FP16 = 5e-3  # relative tolerance of the model's errors (see pose_tolerance.py); references are exact


def trajectory_path(run, key: str) -> Path:
    return run.dataset.joinpath(*key.split("/"))


def frame_files(run, key: str) -> list[Path]:
    patient, lobe, traj = key.split("/")
    return sorted((run.dataset / patient / lobe).glob(f"t{int(traj):03d}_f*.png"))


def write_video(frames: list[Path], path: Path) -> Path:
    """A lossless H.264 (libx264rgb, crf 0, RGB) mp4 of the frames."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264rgb", rate=10, options={"crf": "0", "preset": "ultrafast"})
        first = np.asarray(Image.open(frames[0]).convert("RGB"))
        stream.height, stream.width = first.shape[:2]
        stream.pix_fmt = "rgb24"
        for f in frames:
            image = av.VideoFrame.from_ndarray(np.asarray(Image.open(f).convert("RGB")), format="rgb24")
            for packet in stream.encode(image):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def logged_row(run, key: str) -> pd.Series:
    patient, lobe, traj = key.split("/")
    e = run.errors
    return e[(e.patient == patient) & (e.lobe == lobe) & (e.trajectory == traj)].iloc[0]


def gt_poses(run, key: str) -> np.ndarray:
    patient, lobe, traj = key.split("/")
    table = pd.read_csv(run.dataset / f"{patient}.csv", dtype={"trajectory": str})
    rows = table[(table.lobe == lobe) & (table.trajectory == traj)].sort_values("frame")
    return rows[list(DISK_POSE_COLUMNS)].to_numpy(float)


def track(cli, run, *args):
    return cli("track", *map(str, args), "--config", run.root / "experiments.yaml", "--quiet")


def test_track_a_test_trajectory_writes_csv_png_and_the_runs_logged_errors(cli, tiny_run, tmp_path):
    key = tiny_run.test_keys()[0]
    code, out, err = track(cli, tiny_run, "--run", tiny_run.run_id, trajectory_path(tiny_run, key), "--out", tmp_path)
    assert code == 0, err
    table = pd.read_csv(tmp_path / "trajectory.csv")
    gt = gt_poses(tiny_run, key)
    assert len(table) == len(gt) and (tmp_path / "trajectory.png").stat().st_size > 10_000
    np.testing.assert_allclose(table[list(DISK_POSE_COLUMNS)].to_numpy()[0], gt[0])  # chained from the GT start
    logged = logged_row(tiny_run, key)
    errors = pd.read_csv(tmp_path / "errors.csv").iloc[0]
    assert set(errors.index) == set(logged.index)  # the same table, traj.* metrics included
    refs = columns(tiny_run.errors, "zero_motion") + columns(tiny_run.errors, "train_mean")
    model = columns(tiny_run.errors, "model")
    assert any(".traj." in c for c in model)
    np.testing.assert_allclose(errors[refs].astype(float), logged[refs].astype(float), rtol=1e-9)
    np.testing.assert_allclose(errors[model].astype(float), logged[model].astype(float), rtol=FP16)
    # The printed table shows the same numbers (model, zero motion, training mean).
    line = next(ln for ln in out.splitlines() if ln.lstrip("│ ").startswith("pos_l2 (vox)") and "per pair" in ln)
    shown = [float(v) for v in line.replace("│", " ").split()[-3:]]
    np.testing.assert_allclose(shown, [logged[f"{s}.pair.pos_l2"] for s in ("model", "zero_motion", "train_mean")],
                               rtol=FP16)
    # The chained poses are the relative predictions accumulated in the run's pose frame.
    rel = table[["d_x", "d_y", "d_z", "d_rx", "d_ry", "d_rz"]].to_numpy()[1:]
    np.testing.assert_allclose(table[list(DISK_POSE_COLUMNS)].to_numpy(), geometry.accumulate(gt[0], rel, "world"),
                               atol=1e-6)


def test_a_lossless_video_of_the_frames_gives_the_same_trajectory_and_errors(cli, tiny_run, tmp_path):
    key = tiny_run.test_keys()[1]
    from_frames, from_video = tmp_path / "frames", tmp_path / "video"
    assert track(cli, tiny_run, "--run", tiny_run.run_id, trajectory_path(tiny_run, key), "-o", from_frames)[0] == 0
    video = write_video(frame_files(tiny_run, key), tmp_path / "clip.mp4")
    code, out, err = track(cli, tiny_run, "--run", tiny_run.run_id, video, "-o", from_video,
                           "--ground-truth", trajectory_path(tiny_run, key))
    assert code == 0, err
    a, b = pd.read_csv(from_frames / "trajectory.csv"), pd.read_csv(from_video / "trajectory.csv")
    np.testing.assert_allclose(b[list(DISK_POSE_COLUMNS)], a[list(DISK_POSE_COLUMNS)], atol=1e-6)
    assert list(b.source) == list(range(len(b)))  # video frames are numbered
    model = columns(tiny_run.errors, "model")
    np.testing.assert_allclose(pd.read_csv(from_video / "errors.csv")[model].iloc[0].astype(float),
                               logged_row(tiny_run, key)[model].astype(float), rtol=FP16)


def test_a_folder_of_frames_without_ground_truth_starts_at_the_given_or_identity_pose(cli, tiny_run, tmp_path):
    key = tiny_run.test_keys()[0]
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(frame_files(tiny_run, key)):
        shutil.copy(f, folder / f"img{i}.png")  # natural order: img2 before img10
    code, out, err = track(cli, tiny_run, "--run", tiny_run.run_id, folder, "-o", tmp_path / "a")
    assert code == 0, err
    a = pd.read_csv(tmp_path / "a" / "trajectory.csv")
    assert not (tmp_path / "a" / "errors.csv").exists()
    assert (a[list(DISK_POSE_COLUMNS)].iloc[0] == 0).all() and a.source.iloc[0] == "img0.png"
    code, _, err = track(cli, tiny_run, "--run", tiny_run.run_id, folder, "-o", tmp_path / "b",
                         "--first-pose", "1,2,3,10,20,30")
    assert code == 0, err
    b = pd.read_csv(tmp_path / "b" / "trajectory.csv")
    rel = a[["d_x", "d_y", "d_z", "d_rx", "d_ry", "d_rz"]].to_numpy()[1:]
    np.testing.assert_allclose(b[list(DISK_POSE_COLUMNS)].to_numpy(),
                               geometry.accumulate(np.array([1, 2, 3, 10, 20, 30.0]), rel, "world"), atol=1e-6)


def test_a_registered_model_and_the_best_run_of_a_table_track_like_the_run(cli, tiny_run, tmp_path):
    key = tiny_run.test_keys()[0]
    path = trajectory_path(tiny_run, key)
    code, out, err = track(cli, tiny_run, "--run", tiny_run.run_id, path, "-o", tmp_path / "run",
                           "--register", "tiny-pose")
    assert code == 0, err
    version = out.split("registered as models:/tiny-pose/")[1].split()[0]
    code, _, err = track(cli, tiny_run, "--model", f"models:/tiny-pose/{version}", path, "-o", tmp_path / "reg")
    assert code == 0, err
    code, out, err = track(cli, tiny_run, "--best", "personalized", path, "-o", tmp_path / "best")
    assert code == 0, err
    assert f"run {tiny_run.run_id}" in " ".join(out.split())
    a = pd.read_csv(tmp_path / "run" / "trajectory.csv")
    for other in ("reg", "best"):
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / other / "trajectory.csv"), a)


@pytest.fixture
def bare_run(tiny_run) -> str:
    """A FINISHED run of the experiment that logged no model (runs.model_artifact: none)."""
    client = client_for(tiny_run.cfg)
    run = client.create_run(experiment_id(client, tiny_run.cfg))
    client.set_terminated(run.info.run_id, "FINISHED")
    return run.info.run_id


def test_bad_inputs_are_one_line_and_exit_2(cli, tiny_run, tmp_path, bare_run):
    path = trajectory_path(tiny_run, tiny_run.test_keys()[0])
    empty = tmp_path / "empty"
    empty.mkdir()
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    Image.new("RGB", (32, 32)).save(mixed / "a.png")
    Image.new("RGB", (48, 32)).save(mixed / "b.png")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video at all" * 100)
    run = ("--run", tiny_run.run_id)
    cases = [
        ((*run, empty), "no frames"),
        ((*run, mixed), "48x32 pixels, a.png is 32x32"),
        ((*run, junk), "junk.mp4: not a readable video"),
        ((*run, tmp_path / "nowhere"), "not found"),
        (("--run", bare_run, path), f"run {bare_run} has no MLflow model"),
        (("--run", "0" * 32, path), "no such MLflow run"),
        ((*run, path, "--first-pose", "1,2"), "--first-pose '1,2': expected six numbers"),
        ((path,), "give exactly one of --run, --model, --best"),
        (("--model", "models:/nobody/1", path), "no such registered model version"),
        (("--best", "sota", path), "--best 'sota': must be one of personalized, cross-subject"),
    ]
    for args, message in cases:
        code, out, err = track(cli, tiny_run, *args, "-o", tmp_path / "out")
        assert code == 2, (args, out, err)
        assert message in " ".join(err.split()) and len(err.strip().splitlines()) == 1, (args, err)


def test_frames_of_another_size_are_resized_with_a_printed_warning(cli, tiny_run, tmp_path):
    folder = tmp_path / "big"
    folder.mkdir()
    for f in frame_files(tiny_run, tiny_run.test_keys()[0]):
        Image.open(f).resize((48, 48), Image.Resampling.BILINEAR).save(folder / f.name)
    code, out, err = track(cli, tiny_run, "--run", tiny_run.run_id, folder, "-o", tmp_path / "out")
    assert code == 0, err
    assert "warning:" in out and "48x48 pixels, the network takes 32x32" in " ".join(out.split())
    assert np.isfinite(pd.read_csv(tmp_path / "out" / "trajectory.csv")[list(DISK_POSE_COLUMNS)].to_numpy()).all()
