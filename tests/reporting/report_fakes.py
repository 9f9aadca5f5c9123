"""Fabricated sweeps for the report tests and benchmark: real MLflow runs on a temporary SQLite store.

The runs are made through ``MlflowClient`` exactly as training makes them
(tags, final metrics, params, a ``predictions.csv`` artifact, terminal
status), with metric values chosen by hand so the expected tables are known.
``benchmarks/bench_report.py`` uses it for its 500-run store.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd

os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")

SWEEP = "golden"
EXPERIMENT = "golden-exp"
METRIC_NAMES = ("pos_l2", "rot_l2", "de", "ce")
N_TRAJ, N_PAIRS = 12, 468

# Accumulated means (pos_l2 vox, rot_l2 deg, de rad, ce) of the personalized cells; per pair = these / 100,
# std = mean / 2. conv3d/ce has only a FAILED run; lstm/ce also has an older FINISHED duplicate (ACC_OLD).
ACC = {
    ("baseline", "mse"): (5.0, 20.0, 0.30, 0.060),
    ("baseline", "de"): (4.0, 18.0, 0.25, 0.050),
    ("baseline", "ce"): (4.5, 16.0, 0.28, 0.040),
    ("lstm", "mse"): (3.5, 15.0, 0.22, 0.045),
    ("lstm", "de"): (3.0, 14.0, 0.20, 0.035),
    ("lstm", "ce"): (2.5, 12.0, 0.21, 0.030),
    ("conv3d", "mse"): (6.0, 22.0, 0.35, 0.070),
    ("conv3d", "de"): (5.5, 21.0, 0.33, 0.065),
    ("convlstm", "mse"): (2.8, 12.0, 0.19, 0.032),
    ("convlstm", "de"): (2.2, 13.0, 0.15, 0.028),
    ("convlstm", "ce"): (2.0, 12.5, 0.17, 0.025),
    ("offsetnet", "mse"): (7.0, 25.0, 0.40, 0.080),
    ("offsetnet", "ce"): (6.5, 24.0, 0.38, 0.075),
}
ACC_OLD = (9.9, 99.0, 0.99, 0.099)
N_PARAMS = {"baseline": 13_967_000, "lstm": 14_164_000, "conv3d": 13_983_000, "convlstm": 14_142_000,
            "offsetnet": 43_600_000}

# Cross-subject: per (arch, loss), per fold: (acc means, n trajectories, n pairs); std = mean / 4.
CROSS = {
    ("convlstm", "ce"): {"p00": ((3.0, 14.0, 0.20, 0.030), 4, 150), "p01": ((5.0, 16.0, 0.24, 0.050), 6, 210)},
    ("conv3d", "ce"): {"p00": ((4.0, 15.0, 0.22, 0.040), 4, 150), "p01": ((4.0, 17.0, 0.26, 0.044), 6, 210)},
    ("lstm", "ce"): {"p00": ((3.5, 13.0, 0.30, 0.036), 4, 150), "p01": ((3.9, 15.0, 0.32, 0.038), 6, 210)},
    ("baseline", "mse"): {"p00": ((6.0, 20.0, 0.40, 0.060), 4, 150), "p01": ((7.0, 22.0, 0.42, 0.070), 6, 210)},
    ("convlstm", "de"): {"p00": ((2.0, 10.0, 0.10, 0.020), 4, 150)},  # fold p01 missing
}

PROFILES = {
    arch: {"arch": arch, "params": n, "latency_ms_b1": lat, "gmacs_per_pair": gmac, "device": "cpu (2 threads)",
           "image_size": 64, "window": 10, "batch": 8, "precision": "32"}
    for (arch, n), lat, gmac in zip(N_PARAMS.items(), (3.5, 3.9, 4.4, 3.8, 9.1), (0.41, 0.42, 0.55, 0.43, 1.23))
}


def metrics_from(acc: tuple[float, ...], n_traj: int, n_pairs: int, std_div: float = 2.0,
                 n_params: int | None = None) -> dict[str, float]:
    out: dict[str, float] = {"test.n_trajectories": n_traj, "test.n_pairs": n_pairs}
    for name, value in zip(METRIC_NAMES, acc):
        for prefix, scale in (("acc", 1.0), ("pair", 0.01)):
            out[f"{prefix}.{name}.mean"] = value * scale
            out[f"{prefix}.{name}.std"] = value * scale / std_div
    if n_params is not None:
        out["n_params"] = n_params
    return out


def predictions_frame(seed: int, drift: float, lobes=("ur", "br", "ul", "bl"), n_frames: int = 20) -> pd.DataFrame:
    """A predictions.csv: one trajectory per lobe of patient p00; prediction = truth + drift * frame on x."""
    rows = []
    for t, lobe in enumerate(lobes):
        k = np.arange(n_frames, dtype=float)
        gt = np.stack([10 + k, 20 + 3 * np.sin(k / 4 + t), 30 + 3 * np.cos(k / 4 + t), 0 * k, 2 * k, 0 * k], 1)
        pred = gt.copy()
        pred[:, 0] += drift * k
        for i in range(n_frames):
            row = {"patient": "p00", "lobe": lobe, "trajectory": str(t), "frame": i}
            for j, c in enumerate(("x", "y", "z", "rx", "ry", "rz")):
                row[f"gt_abs_{c}"], row[f"pred_abs_{c}"] = gt[i, j], pred[i, j]
                row[f"gt_rel_{c}"] = np.nan if i == 0 else gt[i, j] - gt[i - 1, j]
                row[f"pred_rel_{c}"] = np.nan if i == 0 else pred[i, j] - pred[i - 1, j]
            rows.append(row)
    return pd.DataFrame(rows)


def fabricate_run(client, exp_id: str, *, arch: str, rot_loss: str, population: str, fold: str = "",
                  seed: int = 0, pose_frame: str = "world", sweep: str = SWEEP, metrics: Mapping[str, float] = (),
                  status: str = "FINISHED", start_time: int | None = None, kind: str = "cell",
                  predictions: pd.DataFrame | None = None, params: Mapping[str, str] | None = None,
                  failure_reason: str = "") -> str:
    """One run as `bronchopose train` leaves it: tags, metrics (step 0), optional artifact, terminal status."""
    from mlflow.entities import Metric, Param, RunTag

    tags = {"arch": arch, "rot_loss": rot_loss, "population": population, "fold": fold, "seed": str(seed),
            "pose_frame": pose_frame, "cell_key": f"{arch}-{rot_loss}-{population}-{fold}-{seed}",
            "sweep": sweep, "run_kind": kind, "dataset_fingerprint": "fab", "failure_reason": failure_reason}
    run = client.create_run(exp_id, start_time=start_time, tags={"mlflow.runName": f"{arch}-{rot_loss}"})
    run_id = run.info.run_id
    ts = start_time or 0
    client.log_batch(run_id, metrics=[Metric(k, float(v), ts, 0) for k, v in dict(metrics).items()],
                     params=[Param(k, v) for k, v in (params or {}).items()],
                     tags=[RunTag(k, v) for k, v in tags.items()])
    if predictions is not None:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "predictions.csv"
            predictions.to_csv(path, index=False)
            client.log_artifact(run_id, str(path))
    client.set_terminated(run_id, status, end_time=(start_time or 0) + 1000 if start_time else None)
    return run_id


def new_store(root: Path, experiment: str = EXPERIMENT):
    """A fresh SQLite MLflow store under ``root``: (client, experiment id, tracking uri)."""
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{root / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    exp_id = client.create_experiment(experiment, artifact_location=(root / "artifacts").as_uri())
    return client, exp_id, uri


def fabricate_golden(client, exp_id: str) -> dict[str, str]:
    """The golden sweep; returns ``{label: run_id}`` (labels like ``personalized/lstm/ce``)."""
    ids: dict[str, str] = {}
    t0 = 1_700_000_000_000
    for i, ((arch, loss), acc) in enumerate(ACC.items()):
        preds = None
        if (arch, loss) in (("convlstm", "ce"), ("offsetnet", "mse")) or loss == "ce":
            preds = predictions_frame(i, drift={"convlstm": 0.1, "offsetnet": 0.4}.get(arch, 0.2))
        ids[f"personalized/{arch}/{loss}"] = fabricate_run(
            client, exp_id, arch=arch, rot_loss=loss, population="personalized", start_time=t0 + 10_000 * (i + 1),
            metrics=metrics_from(acc, N_TRAJ, N_PAIRS, n_params=N_PARAMS[arch]), predictions=preds)
    ids["personalized/lstm/ce-old"] = fabricate_run(
        client, exp_id, arch="lstm", rot_loss="ce", population="personalized", start_time=t0,
        metrics=metrics_from(ACC_OLD, N_TRAJ, N_PAIRS, n_params=N_PARAMS["lstm"]))
    ids["personalized/conv3d/ce-failed"] = fabricate_run(
        client, exp_id, arch="conv3d", rot_loss="ce", population="personalized", start_time=t0 + 5, status="FAILED",
        failure_reason="FloatingPointError: loss is nan")
    # Noise the report must ignore: a tuning trial and a run of another sweep.
    fabricate_run(client, exp_id, arch="convlstm", rot_loss="ce", population="personalized", kind="trial",
                  start_time=t0 + 999_999, metrics=metrics_from(ACC_OLD, 1, 1))
    fabricate_run(client, exp_id, arch="convlstm", rot_loss="ce", population="personalized", sweep="other",
                  start_time=t0 + 999_999, metrics=metrics_from(ACC_OLD, 1, 1))
    for i, ((arch, loss), folds) in enumerate(CROSS.items()):
        for j, (fold, (acc, n_traj, n_pairs)) in enumerate(folds.items()):
            ids[f"cross-subject/{arch}/{loss}/{fold}"] = fabricate_run(
                client, exp_id, arch=arch, rot_loss=loss, population="cross-subject", fold=fold,
                start_time=t0 + 500_000 + 100 * i + j, metrics=metrics_from(acc, n_traj, n_pairs, std_div=4.0))
    return ids
