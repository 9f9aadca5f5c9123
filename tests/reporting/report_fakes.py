"""Fabricated sweeps for the report tests and benchmark: real MLflow runs on a temporary SQLite store.

The runs are made through ``MlflowClient`` exactly as training makes them
(tags incl. ``cell_key``, final metrics, params, ``trajectory_errors.csv`` and
``predictions.csv`` artifacts, terminal status). Per-trajectory errors are
planted: error = mean x trajectory difficulty (shared by every model, as real
test trajectories are easy or hard for all) x (1 + small noise per run), so
rows whose planted means differ by >= 8 % are told apart by the paired test
and rows that differ by < 1 % are not. ``benchmarks/bench_report.py`` uses
``fabricate_run`` and ``metrics_from`` for its 500-run store.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")

SWEEP = "golden"
EXPERIMENT = "golden-exp"
METRIC_NAMES = ("pos_l2", "rot_l2", "de", "ce")
LOBES = ("ur", "br", "ul", "bl")
PATIENTS = ("p00", "p01", "p02")
SEEDS = (0, 1, 2)  # 3: the fewest with intervals and marks (2 seeds show means only)

# Accumulated means (pos_l2 vox, rot_l2 deg, de rad, ce) of the personalized cells; per pair = these / 100.
# Planted outcomes: position L2 convlstm/ce is the single best (10 % below the next); rotation L2 lstm/ce and
# convlstm/mse tie (0.4 % apart); conv3d/ce has only a FAILED run (seed 0) and none for seeds 1-2; lstm/ce seed 0
# also has an older FINISHED duplicate; conv3d/mse ignores its input (pred.std_ratio.pos 0.01).
ACC = {
    ("baseline", "mse"): (4.8, 20.0, 0.30, 0.060),
    ("baseline", "de"): (4.0, 18.0, 0.25, 0.050),
    ("baseline", "ce"): (4.5, 16.0, 0.28, 0.040),
    ("lstm", "mse"): (3.5, 15.0, 0.22, 0.045),
    ("lstm", "de"): (3.0, 14.0, 0.20, 0.035),
    ("lstm", "ce"): (2.5, 12.0, 0.21, 0.030),
    ("conv3d", "mse"): (6.0, 22.0, 0.35, 0.070),
    ("conv3d", "de"): (5.5, 21.0, 0.33, 0.065),
    ("convlstm", "mse"): (2.8, 12.05, 0.19, 0.032),
    ("convlstm", "de"): (2.2, 13.0, 0.15, 0.028),
    ("convlstm", "ce"): (2.0, 13.0, 0.17, 0.025),
    ("offsetnet", "mse"): (7.0, 25.0, 0.40, 0.080),
}
REFS = {"zero_motion": (6.2, 24.0, 0.36, 0.075), "train_mean": (5.8, 23.0, 0.34, 0.072)}
ACC_OLD = (9.9, 99.0, 0.99, 0.099)
IGNORES = {("conv3d", "mse")}
N_PARAMS = {"baseline": 13_967_000, "lstm": 14_164_000, "conv3d": 13_983_000, "convlstm": 14_142_000,
            "offsetnet": 43_600_000}

# Cross-subject: the 3 combinations the recorded selection keeps; per fold the accumulated means.
# convlstm/de has no run for fold p01 seed 1 (that replicate is incomplete).
CROSS = {
    ("convlstm", "ce"): {"p00": (3.0, 14.0, 0.20, 0.030), "p01": (5.0, 16.0, 0.24, 0.050),
                         "p02": (4.0, 15.0, 0.22, 0.040)},
    ("convlstm", "de"): {"p00": (2.0, 10.0, 0.10, 0.020), "p01": (2.5, 11.0, 0.12, 0.022),
                         "p02": (2.2, 10.5, 0.11, 0.021)},
    ("lstm", "ce"): {"p00": (3.5, 13.0, 0.30, 0.036), "p01": (3.9, 15.0, 0.32, 0.038),
                     "p02": (3.7, 14.0, 0.31, 0.037)},
}
CROSS_SELECTED = [{"arch": a, "rot_loss": lo} for a, lo in CROSS]
SOTA_SELECTED = [{"arch": "convlstm", "rot_loss": "de"}]  # BronchoTrack is whatever the sota stage selected

PROFILES = {
    arch: {"arch": arch, "params": n, "latency_ms_b1": lat, "gmacs_per_pair": gmac, "device": "cpu (2 threads)",
           "image_size": 64, "window": 10, "batch": 8, "precision": "32"}
    for (arch, n), lat, gmac in zip(N_PARAMS.items(), (3.5, 3.9, 4.4, 3.8, 9.1), (0.41, 0.42, 0.55, 0.43, 1.23))
}

GOLDEN_CONFIG = """name: {sweep}
runs: {{uri: "{uri}", experiment: {experiment}}}
dataset: {{root: {data}}}
splits: {{train: 2, val: 1, test: 2, cross_subject_val: 1}}
grid: {{arch: [baseline, lstm, conv3d, convlstm, offsetnet], rot_loss: [mse, de, ce], population: [personalized],
       folds: [p00, p01, p02], seed: [0, 1, 2], pose_frame: [world]}}
train: {{steps: 300, batch_size: 20}}
stages:
  - name: personalized
    grid: {{arch: [baseline, lstm, conv3d, convlstm], population: [personalized]}}
  - name: cross-subject
    select: {{top: 3, by: val_best.pos_l2, over: [arch, rot_loss]}}
    grid: {{population: [cross-subject]}}
  - name: sota
    source: personalized
    select: {{top: 1, by: val_best.pos_l2, over: [arch, rot_loss]}}
    grid: {{population: [personalized]}}
    add: [{{arch: offsetnet, rot_loss: mse}}]
"""


# -- planted per-trajectory errors ----------------------------------------------------------------------


def trajectory_keys(patients: Sequence[str] = PATIENTS, per_lobe: int = 2) -> list[tuple[str, str, str]]:
    return [(p, lobe, f"{lobe}{k}") for p in patients for lobe in LOBES for k in range(per_lobe)]


def difficulty(keys: Sequence[tuple[str, str, str]], seed: int = 7, spread: float = 0.2) -> dict:
    """Per trajectory and scope, a multiplicative difficulty (mean 1) every model and reference shares."""
    rng = np.random.default_rng(seed)
    acc, pair = np.exp(spread * rng.standard_normal((2, len(keys))))
    n = rng.integers(15, 31, len(keys))
    acc, pair = acc / acc.mean(), pair / (np.sum(n * pair) / n.sum())  # the planted means are the table's
    return {k: {"acc": float(a), "pair": float(p), "n_pairs": int(m)} for k, a, p, m in zip(keys, acc, pair, n)}


def errors_frame(keys: Sequence[tuple[str, str, str]], acc: Sequence[float], rng: np.random.Generator, *,
                 refs: Mapping[str, Sequence[float]] = REFS, noise: float = 0.05, hard: dict | None = None,
                 scale: float = 1.0) -> pd.DataFrame:
    """A trajectory_errors.csv: per trajectory the model's (x ``scale``) and both references' errors, planted
    (module doc)."""
    hard = hard or difficulty(keys)
    rows = []
    for k in keys:
        h = hard[k]
        row: dict[str, object] = {"patient": k[0], "lobe": k[1], "trajectory": k[2], "n_pairs": h["n_pairs"]}
        for source, means in (("model", acc), *refs.items()):
            jitter, level = (noise, scale) if source == "model" else (0.0, 1.0)
            for scope, factor in (("acc", 1.0), ("pair", 0.01)):
                for name, mu in zip(METRIC_NAMES, means):
                    value = mu * level * factor * h[scope] * (1.0 + jitter * rng.standard_normal())
                    row[f"{source}.{scope}.{name}"] = value
                row[f"{source}.{scope}.pos_l2_mm"] = row[f"{source}.{scope}.pos_l2"] * 0.5  # type: ignore[operator]
                row[f"{source}.{scope}.geodesic"] = row[f"{source}.{scope}.rot_l2"]
            row |= tracking_columns(source, float(row[f"{source}.acc.pos_l2"]),  # type: ignore[arg-type]
                                    float(row[f"{source}.acc.rot_l2"]))  # type: ignore[arg-type]
        rows.append(row)
    return pd.DataFrame(rows)


TRACKING = ("ctf", "ctf_mm", "ate", "ate_mm", "rpe_trans", "rpe_rot", "drift")
THRESHOLDS = {"eval.ctf_position": 5.0, "eval.ctf_position_mm": 5.0, "eval.ctf_angle": 10.0, "eval.rpe_gap": 10.0}


def tracking_columns(source: str, pos: float, rot: float) -> dict[str, float]:
    """A trajectory's camera-tracking metrics, planted as functions of its endpoint errors (no random draw, so
    the other planted columns stay what they were): larger errors, lower CTF."""
    return {f"{source}.traj.ctf": 100.0 * float(np.exp(-pos / 4.0 - rot / 40.0)),
            f"{source}.traj.ctf_mm": 100.0 * float(np.exp(-pos / 8.0 - rot / 40.0)),
            f"{source}.traj.ate": 0.6 * pos, f"{source}.traj.ate_mm": 0.3 * pos,
            f"{source}.traj.rpe_trans": 0.2 * pos, f"{source}.traj.rpe_rot": 0.3 * rot,
            f"{source}.traj.drift": 2.0 * pos}


def metrics_from_errors(df: pd.DataFrame, n_params: int | None = None, *, ratio: float = 0.5, steps: int = 300,
                        epochs: float = 3.0) -> dict[str, float]:
    """The run-level metrics training logs, consistent with the per-trajectory table ``df``."""
    w = df["n_pairs"].to_numpy(dtype=float)
    out: dict[str, float] = {"test.n_trajectories": float(len(df)), "test.n_pairs": float(w.sum())}
    for source in ("model", "zero_motion", "train_mean"):
        prefix = "" if source == "model" else f"{source}."
        for name in (*METRIC_NAMES, "pos_l2_mm", "geodesic"):
            pair = df[f"{source}.pair.{name}"].to_numpy(dtype=float)
            acc = df[f"{source}.acc.{name}"].to_numpy(dtype=float)
            out[f"{prefix}pair.{name}.mean"] = float(np.sum(w * pair) / w.sum())
            out[f"{prefix}pair.{name}.std"] = float(pair.std())
            out[f"{prefix}acc.{name}.mean"] = float(acc.mean())
            out[f"{prefix}acc.{name}.std"] = float(acc.std())
        for name in TRACKING:
            if f"{source}.traj.{name}" in df:
                values = df[f"{source}.traj.{name}"].to_numpy(dtype=float)
                out[f"{prefix}traj.{name}.mean"] = float(values.mean())
                out[f"{prefix}traj.{name}.std"] = float(values.std())
    out |= THRESHOLDS
    out |= {"pred.std.pos": ratio * 2.0, "pred.std.rot": ratio * 3.0, "pred.std_ratio.pos": ratio,
            "pred.std_ratio.rot": ratio, "train.steps": float(steps), "train.pairs_seen": float(steps * 20),
            "train.epochs": epochs, "train.best_step": float(steps), "train.train_pairs": 400.0,
            "train.train_trajectories": 16.0, "val_best.pos_l2": float(out["pair.pos_l2.mean"])}
    if n_params is not None:
        out["n_params"] = float(n_params)
    return out


def metrics_from(acc: tuple[float, ...], n_traj: int, n_pairs: int, std_div: float = 2.0,
                 n_params: int | None = None) -> dict[str, float]:
    """Run-level metrics alone (no per-trajectory table): what a run made before trajectory_errors.csv logged."""
    out: dict[str, float] = {"test.n_trajectories": n_traj, "test.n_pairs": n_pairs}
    for name, value in zip(METRIC_NAMES, acc):
        for prefix, scale in (("acc", 1.0), ("pair", 0.01)):
            out[f"{prefix}.{name}.mean"] = value * scale
            out[f"{prefix}.{name}.std"] = value * scale / std_div
    if n_params is not None:
        out["n_params"] = n_params
    return out


def predictions_frame(seed: int, drift: float, lobes=LOBES, n_frames: int = 20) -> pd.DataFrame:
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


# -- MLflow runs ------------------------------------------------------------------------------------------


def fabricate_run(client, exp_id: str, *, arch: str, rot_loss: str, population: str, fold: str = "",
                  seed: int = 0, pose_frame: str = "world", sweep: str = SWEEP, metrics: Mapping[str, float] = (),
                  status: str = "FINISHED", start_time: int | None = None, kind: str = "cell",
                  predictions: pd.DataFrame | None = None, params: Mapping[str, str] | None = None,
                  failure_reason: str = "", cell_key: str | None = None, train_trajectories: str = "",
                  errors: pd.DataFrame | None = None, stop_reason: str = "budget") -> str:
    """One run as `bronchopose train` leaves it: tags, metrics (step 0), optional artifacts, terminal status."""
    from mlflow.entities import Metric, Param, RunTag

    key = cell_key if cell_key is not None else f"{arch}-{rot_loss}-{population}-{fold}-{seed}-{train_trajectories}"
    tags = {"arch": arch, "rot_loss": rot_loss, "population": population, "fold": fold, "seed": str(seed),
            "pose_frame": pose_frame, "train_trajectories": train_trajectories, "cell_key": key,
            "sweep": sweep, "run_kind": kind, "dataset_fingerprint": "fab", "failure_reason": failure_reason,
            "init": "random"}
    if status == "FINISHED":
        tags["stop_reason"] = stop_reason
    run = client.create_run(exp_id, start_time=start_time, tags={"mlflow.runName": f"{arch}-{rot_loss}"})
    run_id = run.info.run_id
    ts = start_time or 0
    client.log_batch(run_id, metrics=[Metric(k, float(v), ts, 0) for k, v in dict(metrics).items()],
                     params=[Param(k, v) for k, v in (params or {}).items()],
                     tags=[RunTag(k, v) for k, v in tags.items()])
    with tempfile.TemporaryDirectory() as tmp:
        for name, frame in (("predictions.csv", predictions), ("trajectory_errors.csv", errors)):
            if frame is not None:
                path = Path(tmp) / name
                frame.to_csv(path, index=False)
                client.log_artifact(run_id, str(path))
    client.set_terminated(run_id, status, end_time=(start_time or 0) + 1000 if start_time else None)
    return run_id


def fabricate_selection(client, exp_id: str, *, sweep: str, stage: str, plan_key: str, selected: list[dict],
                        start_time: int | None = None, by: str = "val_best.pos_l2") -> str:
    """A ``run_kind=selection`` run as ``sweep.plan`` records one."""
    run = client.create_run(exp_id, start_time=start_time, tags={
        "sweep": sweep, "run_kind": "selection", "stage": stage, "plan_key": plan_key,
        "mlflow.runName": f"selection-{stage}"})
    for k, v in {"by": by, "top": str(len(selected)), "selected": json.dumps(selected)}.items():
        client.log_param(run.info.run_id, k, v)
    client.set_terminated(run.info.run_id, "FINISHED")
    return run.info.run_id


def new_store(root: Path, experiment: str = EXPERIMENT):
    """A fresh SQLite MLflow store under ``root``: (client, experiment id, tracking uri)."""
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{root / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    exp_id = client.create_experiment(experiment, artifact_location=(root / "artifacts").as_uri())
    return client, exp_id, uri


def write_config(path: Path, template: str = GOLDEN_CONFIG, **values: object):
    """Write a config from ``template`` and load it: (path, Config)."""
    from bronchocli.config import load_config

    path.write_text(template.format(**values))
    return path, load_config(path)


def fabricate_golden(client, exp_id: str, cfg) -> dict[str, str]:
    """The golden sweep of ``cfg`` (GOLDEN_CONFIG); returns ``{label: run_id}`` (labels like
    ``personalized/lstm/ce/s0``)."""
    from bronchocli.sweep.plan import plan_key

    ids: dict[str, str] = {}
    t0 = 1_700_000_000_000
    rng = np.random.default_rng(0)
    keys = trajectory_keys()
    hard = difficulty(keys)
    key_of = lambda **c: cfg.cell(pose_frame="world", **c).key  # noqa: E731
    figure_runs = {("convlstm", "de"), ("offsetnet", "mse")} | {(a, "ce") for a in N_PARAMS}
    for i, ((arch, loss), acc) in enumerate(ACC.items()):
        for seed in SEEDS:
            df = errors_frame(keys, acc, rng, hard=hard)
            preds = predictions_frame(i, drift=0.1 + 0.05 * i) if seed == 0 and (arch, loss) in figure_runs else None
            metrics = metrics_from_errors(df, N_PARAMS[arch], ratio=0.01 if (arch, loss) in IGNORES else 0.5,
                                          epochs=3.0 + 0.1 * i)
            ids[f"personalized/{arch}/{loss}/s{seed}"] = fabricate_run(
                client, exp_id, arch=arch, rot_loss=loss, population="personalized", seed=seed,
                start_time=t0 + 10_000 * (i + 1) + seed, metrics=metrics, predictions=preds, errors=df,
                cell_key=key_of(arch=arch, rot_loss=loss, population="personalized", seed=seed),
                stop_reason="early_stop" if arch == "lstm" else "budget")
    old = errors_frame(keys, ACC_OLD, rng, hard=hard)
    ids["personalized/lstm/ce/s0-old"] = fabricate_run(
        client, exp_id, arch="lstm", rot_loss="ce", population="personalized", start_time=t0, errors=old,
        metrics=metrics_from_errors(old, N_PARAMS["lstm"]),
        cell_key=key_of(arch="lstm", rot_loss="ce", population="personalized", seed=0))
    ids["personalized/conv3d/ce/s0-failed"] = fabricate_run(
        client, exp_id, arch="conv3d", rot_loss="ce", population="personalized", start_time=t0 + 5, status="FAILED",
        failure_reason="FloatingPointError: loss is nan",
        cell_key=key_of(arch="conv3d", rot_loss="ce", population="personalized", seed=0))
    for j, ((arch, loss), folds) in enumerate(CROSS.items()):
        for seed in SEEDS:
            for fold, acc in folds.items():
                if (arch, loss, fold, seed) == ("convlstm", "de", "p01", 1):
                    continue
                df = errors_frame([k for k in keys if k[0] == fold], acc, rng, hard=hard)
                ids[f"cross-subject/{arch}/{loss}/{fold}/s{seed}"] = fabricate_run(
                    client, exp_id, arch=arch, rot_loss=loss, population="cross-subject", fold=fold, seed=seed,
                    start_time=t0 + 500_000 + 100 * j + 10 * seed + (fold == "p01"), errors=df,
                    metrics=metrics_from_errors(df, N_PARAMS[arch]),
                    cell_key=key_of(arch=arch, rot_loss=loss, population="cross-subject", fold=fold, seed=seed))
    pk = plan_key(cfg)
    fabricate_selection(client, exp_id, sweep=SWEEP, stage="cross-subject", plan_key=pk, selected=CROSS_SELECTED)
    fabricate_selection(client, exp_id, sweep=SWEEP, stage="sota", plan_key=pk, selected=SOTA_SELECTED)
    # Noise the report must ignore: a tuning trial, a run of another sweep, runs of an earlier config of this
    # sweep (other cell keys, newer than the real ones) and a selection recorded under another plan.
    noise = metrics_from(ACC_OLD, 1, 1)
    fabricate_run(client, exp_id, arch="convlstm", rot_loss="ce", population="personalized", kind="trial",
                  start_time=t0 + 999_999, metrics=noise)
    fabricate_run(client, exp_id, arch="convlstm", rot_loss="ce", population="personalized", sweep="other",
                  start_time=t0 + 999_999, metrics=noise)
    for seed in SEEDS:
        stale = errors_frame(keys, ACC_OLD, rng, hard=hard)
        ids[f"stale/lstm/mse/s{seed}"] = fabricate_run(
            client, exp_id, arch="lstm", rot_loss="mse", population="personalized", seed=seed, errors=stale,
            start_time=t0 + 999_000 + seed, metrics=metrics_from_errors(stale), cell_key=f"stale{seed:011d}")
    fabricate_selection(client, exp_id, sweep=SWEEP, stage="sota", plan_key="0ther0plan000000",
                        selected=[{"arch": "baseline", "rot_loss": "mse"}], start_time=t0 + 2_000_000)
    return ids


def fast_sqlite(root: Path) -> None:
    """Skip fsync on the SQLite stores under ``root`` (throwaway test stores): a commit costs ~10 ms otherwise,
    and the golden sweep makes ~300 of them."""
    import sqlite3

    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    prefix = str(Path(root).resolve())

    @event.listens_for(Engine, "connect")
    def _no_sync(dbapi_connection, _record):  # noqa: ANN001 - SQLAlchemy's callback signature
        if type(dbapi_connection).__module__ != "sqlite3":
            return
        try:
            files = [row[2] or "" for row in dbapi_connection.execute("PRAGMA database_list").fetchall()]
            if any(f.startswith(prefix) for f in files):
                dbapi_connection.execute("PRAGMA synchronous=OFF")
        except sqlite3.Error:
            # A locked store (tests/sweep/test_busy.py) must fail only where the product decides: raising from a
            # connect listener makes MLflow's engine creation retry 10 times with backoff (~101 s), not 0.5 s.
            pass


# -- in-memory runs (no MLflow): RunRecords plus a trajectory-errors loader --------------------------------


class MemRuns:
    """Hand-made RunRecords and their trajectory errors, for table tests that need no MLflow store."""

    def __init__(self, seed: int = 0, keys: Sequence[tuple[str, str, str]] | None = None):
        self.rng = np.random.default_rng(seed)
        self.keys = list(keys or trajectory_keys())
        self.hard = difficulty(self.keys)
        self.records: list = []
        self.errors: dict[str, object] = {}

    def add(self, arch: str, loss: str, acc: Sequence[float] | None = (1.0, 10.0, 0.1, 0.01), *,
            population: str = "personalized", fold: str = "", seed: int = 0, frame: str = "world", size: str = "",
            status: str = "FINISHED", start: int = 0, key: str | None = None, noise: float = 0.05,
            refs: Mapping[str, Sequence[float]] | None = None, ratio: float = 0.5, with_errors: bool = True,
            scale: float = 1.0, train_pairs: float | None = None, init: str = "random", **extra: float):
        from bronchocli.reporting.aggregate import RunErrors
        from bronchocli.reporting.collect import RunRecord

        keys = [k for k in self.keys if not fold or k[0] == fold]
        run_id = f"r{len(self.records):03d}"
        tags = {"arch": arch, "rot_loss": loss, "population": population, "fold": fold, "seed": str(seed),
                "pose_frame": frame, "train_trajectories": size, "cell_key": key or f"k-{run_id}",
                "stop_reason": "budget" if status == "FINISHED" else "", "init": init}
        metrics: dict[str, float] = {}
        if acc is not None and status == "FINISHED":
            df = errors_frame(keys, acc, self.rng, hard=self.hard, noise=noise, refs=refs or REFS, scale=scale)
            metrics = metrics_from_errors(df, ratio=ratio)
            if train_pairs is not None:
                metrics["train.train_pairs"] = train_pairs
            if with_errors:
                self.errors[run_id] = RunErrors.from_frame(df)
        metrics |= extra
        rec = RunRecord(run_id, status, start, tags, metrics)
        self.records.append(rec)
        return rec

    def load(self, run):
        return self.errors.get(run.run_id)

    def context(self, plan=None, pose_frame: str | None = None, **kw):
        from bronchocli.reporting.collect import index_runs
        from bronchocli.reporting.tables import ReportContext

        index = index_runs(self.records, "s", "e", pose_frame, plan=plan)
        return ReportContext(index, errors=self.load, **kw)


def frames_runs() -> MemRuns:
    """Runs in both pose frames, each frame with its own references (for the frames table)."""
    m = MemRuns(seed=11)
    for seed in (0, 1, 2):
        # lstm: much better skill with camera labels (error 20 % of the references vs 60 % in world);
        # convlstm: the same skill in both frames. Each frame has its own references (camera ones smaller).
        camera_refs = {"zero_motion": (3.1, 12.0, 0.18, 0.037), "train_mean": (2.9, 11.5, 0.17, 0.036)}
        m.add("lstm", "ce", (3.48, 13.8, 0.20, 0.04), seed=seed, frame="world")
        m.add("lstm", "ce", (0.58, 2.3, 0.03, 0.007), seed=seed, frame="camera", refs=camera_refs)
        m.add("convlstm", "ce", (2.9, 11.5, 0.17, 0.036), seed=seed, frame="world")
        m.add("convlstm", "ce", (1.45, 5.75, 0.085, 0.018), seed=seed, frame="camera", refs=camera_refs)
    return m


def worked_example():
    """docs/reports.md's worked example: Table 3 (per pair) from 4 fabricated networks x 3 seeds, in memory.

    Planted: ConvLSTM 20 % below LSTM in position (a single best), LSTM and ConvLSTM 0.4 % apart in rotation
    (a tie), 3D conv at the references' level with constant predictions (†, ‡).
    """
    from bronchocli.reporting.tables import personalized

    m = MemRuns(seed=21)
    planted = {("baseline", "ce"): (4.5, 16.0, 0.28, 0.040), ("lstm", "ce"): (2.50, 12.0, 0.21, 0.030),
               ("convlstm", "ce"): (2.00, 12.05, 0.17, 0.025), ("conv3d", "ce"): (5.9, 22.5, 0.35, 0.071)}
    for (arch, loss), acc in planted.items():
        for seed in (0, 1, 2):
            m.add(arch, loss, acc, seed=seed, ratio=0.01 if arch == "conv3d" else 0.5)
    return personalized(m.context(), "pair")


def golden_tables(golden):
    """Every table of the golden sweep and of the in-memory frames runs, by key, and the golden context (what
    the golden-file and caption tests read)."""
    from bronchocli.reporting import report, tables
    from bronchocli.reporting.figures import errors_loader

    ctx = tables.ReportContext(report.collect_index(golden.client, golden.cfg), profiler=PROFILES.get,
                               errors=errors_loader(golden.client))
    out = {t.key: t for t in report.build_tables(ctx, list(tables.TABLES), ["accumulated", "pair"])}
    out |= {t.key: t for t in report.build_tables(frames_runs().context(), ["frames"], ["accumulated", "pair"])}
    return out, ctx
