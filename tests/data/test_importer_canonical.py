"""Imported Euler angles are canonicalised: a dataset written in the other XYZ form of its rotations imports, trains
on and reports exactly like its canonical twin (issue 23, item 2).

Every rotation has two XYZ triples, (a, b, c) and (a+180, 180-b, c+180). A foreign CSV may use either, even
switching between them from one frame to the next (an angle unwrapper does that at |b| = 90). Passed through
unchanged, the ``world``-frame labels (angle differences) of such a file jump by ~180° per angle at every switch.
"""

from __future__ import annotations

import numpy as np
import pytest
from tinydata import write_tiny_dataset

from bronchocli import geometry
from bronchocli.config import CsvImport
from bronchocli.data.batches import relative_labels
from bronchocli.data.importer import import_csv
from bronchocli.data.reader import open_dataset_dir
from bronchocli.reporting.aggregate import RunErrors
from bronchocli.reporting.collect import RunRecord, index_runs
from bronchocli.reporting.markdown import to_markdown
from bronchocli.reporting.tables import ReportContext, personalized
from bronchocli.training import evaluate

COLUMNS = {"patient": "patient", "lobe": "lobe", "trajectory": "trajectory", "frame": "frame", "x": "x", "y": "y",
           "z": "z", "rx": "rx", "ry": "ry", "rz": "rz", "filename": None}
SETTINGS = CsvImport(columns=COLUMNS, euler="XYZ", angle_units="deg", spacing_mm=(0.5, 0.5, 0.5))


def other_form(angles: np.ndarray) -> np.ndarray:
    return geometry.wrap_deg(np.column_stack([angles[:, 0] + 180.0, 180.0 - angles[:, 1], angles[:, 2] + 180.0]))


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """The same poses as two CSVs: canonical, and with a random half of the rows in the other form."""
    base = tmp_path_factory.mktemp("twins")
    truth = open_dataset_dir(write_tiny_dataset(base / "ds", patients=2, lobes=("ur", "bl"), trajectories=3,
                                                frames=10, image_size=8))
    f = truth.frames[["patient", "lobe", "trajectory", "frame", "x", "y", "z", "rx", "ry", "rz"]].copy()
    (base / "canonical").mkdir()
    f.to_csv(base / "canonical" / "poses.csv", index=False)
    flip = np.random.default_rng(0).random(len(f)) < 0.5
    angles = f[["rx", "ry", "rz"]].to_numpy().copy()
    angles[flip] = other_form(angles[flip])
    g = f.copy()
    g[["rx", "ry", "rz"]] = angles
    (base / "other").mkdir()
    g.to_csv(base / "other" / "poses.csv", index=False)
    assert (np.abs(g["ry"].to_numpy()[flip]) > 90).all()
    return import_csv(base / "canonical", SETTINGS), import_csv(base / "other", SETTINGS)


def test_imported_angles_are_the_canonical_triples(twins):
    canonical, other = twins
    for t in other.trajectories:
        twin = canonical.trajectory(t.key)
        assert (np.abs(t.poses[:, 4]) <= 90).all()
        np.testing.assert_allclose(t.poses, twin.poses, atol=1e-9)
        for frame in ("world", "camera"):
            np.testing.assert_allclose(relative_labels(t, frame), relative_labels(twin, frame), atol=1e-9)


def _network(ds, frame: str, seed: int) -> list[evaluate.TrajectoryPrediction]:
    """A stand-in network: what it predicts depends on the images (the true motion) and the seed, never on how
    the labels were written, as a real network trained on the same frames would behave."""
    out = []
    for t in ds.trajectories:
        rng = np.random.default_rng([seed, abs(hash(t.key)) % 2**32])
        motion = geometry.relative_trajectory(geometry.canonical_pose(t.poses), frame)
        pred = motion + np.concatenate([rng.normal(0, 0.3, (len(motion), 3)), rng.normal(0, 2, (len(motion), 3))],
                                       1)
        gt_abs = np.asarray(t.poses, dtype=np.float64)
        out.append(evaluate.TrajectoryPrediction(
            key=t.key, patient=t.patient, lobe=t.lobe, traj_id=t.traj_id, gt_rel=relative_labels(t, frame),
            pred_rel=pred, gt_abs=gt_abs, pred_abs=geometry.accumulate(gt_abs[0], pred, frame),
            spacing_mm=np.asarray(ds.spacing_mm(t.patient)), frame=frame))
    return out


def _runs(ds, frame: str):
    train_mean = np.concatenate([relative_labels(t, frame) for t in ds.trajectories]).mean(0)
    records, errors = [], {}
    for i, (arch, seed) in enumerate((a, s) for a in ("lstm", "convlstm") for s in (0, 1)):
        values, table = evaluate.evaluate(_network(ds, frame, seed + 10 * i), train_mean, frame)
        run_id = f"r{i}"
        tags = {"arch": arch, "rot_loss": "ce", "population": "personalized", "fold": "", "seed": str(seed),
                "pose_frame": frame, "train_trajectories": "", "cell_key": f"k{i}"}
        records.append(RunRecord(run_id, "FINISHED", i, tags, values))
        errors[run_id] = RunErrors.from_frame(table)
    return records, errors


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_twins_give_identical_run_metrics_and_report_tables(twins, frame):
    (runs_a, err_a), (runs_b, err_b) = (_runs(ds, frame) for ds in twins)
    for a, b in zip(runs_a, runs_b):
        assert set(a.metrics) == set(b.metrics)
        for k in a.metrics:
            assert b.metrics[k] == pytest.approx(a.metrics[k], rel=1e-7, abs=1e-9, nan_ok=True), k
    assert runs_a[0].metrics["acc.rot_l2.mean"] > 1.0  # real errors, not all zero
    for evaluation in ("accumulated", "pair"):
        tables = []
        for runs, errors in ((runs_a, err_a), (runs_b, err_b)):
            ctx = ReportContext(index_runs(runs, "s", "e", frame), errors=lambda r, e=errors: e.get(r.run_id))
            tables.append(to_markdown(personalized(ctx, evaluation)))
        assert tables[0] == tables[1], evaluation
