"""Report figures from the runs' ``predictions.csv`` artifacts (PNG + PDF, written atomically).

* ``fig5-trajectories``: ground truth vs BronchoTrack (the sota stage's
  selection, else ConvLSTM + MSE+CE) vs
  OffsetNet (MSE+MSE), 3-D in voxel axes, for chosen test trajectories (the
  paper's Figure 5); personalized runs.
* ``fig-error-position`` / ``fig-error-rotation``: every model of Tables 6
  and 7 (each architecture with MSE+CE, BronchoTrack or the sota stage's
  selection, OffsetNet with its own loss; one personalized run each), the
  error of the accumulated pose against the frame index along the test
  trajectories: position L2 in voxels and geodesic angle in degrees, mean ±
  std over trajectories at each frame, and the two image-blind references
  (dashed); the caption under the axes names the seed shown and any model
  left out, and why.

``predictions.csv`` has one row per test frame with ``gt_abs_*``/``pred_abs_*``
(absolute poses, predictions chained from the true first pose).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable, Mapping, Sequence
from urllib.parse import urlparse
from urllib.request import url2pathname

import numpy as np
import pandas as pd

from .. import metrics, registry
from ..runkeys import REFERENCES
from ..cells import LOBES
from ..io import save_figure
from ..plots import error_curve_figure, trajectory_figure
from .aggregate import ERRORS_CSV, read_errors
from .aggregate import REFERENCES as REFERENCE_NAMES  # the references' row names in the tables
from .collect import RunIndex, RunRecord
from .context import ABLATION_LOSS, OFFSETNET, arch_names, bronchotrack

POSE = ("x", "y", "z", "rx", "ry", "rz")
KEY = ("patient", "lobe", "trajectory")
FORMATS = ("png", "pdf")
Key = tuple[str, str, str]
Loader = Callable[[RunRecord], "object | None"]  # run -> predictions DataFrame or None


def read_predictions(path: Path):
    """A predictions.csv as a DataFrame with string trajectory keys."""
    return pd.read_csv(path, dtype={k: str for k in KEY})


def local_artifact(run: RunRecord, name: str) -> Path | None:
    """Where a run's artifact ``name`` lies when its artifact store is a local folder (None otherwise)."""
    uri = run.artifact_uri
    if uri.startswith("file:"):
        return Path(url2pathname(urlparse(uri).path)) / name
    if uri and "://" not in uri:
        return Path(uri) / name
    return None


def artifact_loader(client, name: str, read: Callable[[Path], object], warnings: list[str] | None,
                    what: str = "figures") -> Loader:
    """Loader downloading one artifact of each run and reading it; a missing one is None (and a warning when
    ``warnings`` is given)."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # no tqdm bar per download

    def load(run: RunRecord):
        local = local_artifact(run, name)
        if local is not None:  # a file store: read in place (a download costs ~30 ms a run)
            if local.is_file():
                return read(local)
            if warnings is not None:
                warnings.append(f"{what}: run {run.run_id} ({run.label}) has no {name} artifact")
            return None
        with tempfile.TemporaryDirectory() as tmp:
            try:
                path = client.download_artifacts(run.run_id, name, tmp)
            except Exception as exc:  # noqa: BLE001 - any store error means "no such artifact for this run"
                if warnings is not None:
                    warnings.append(f"{what}: run {run.run_id} ({run.label}) has no {name} artifact "
                                    f"({type(exc).__name__})")
                return None
            return read(Path(path))
    return load


def mlflow_loader(client, warnings: list[str]) -> Loader:
    """Loader of each run's ``predictions.csv`` artifact; a missing one becomes a warning."""
    return artifact_loader(client, "predictions.csv", read_predictions, warnings)


def errors_loader(client) -> Loader:
    """Loader of each run's ``trajectory_errors.csv`` (the tables say which rows lack it, once per table)."""
    return artifact_loader(client, ERRORS_CSV, read_errors, None)


def trajectory_keys(df) -> list[Key]:
    return [tuple(map(str, k)) for k in df[list(KEY)].drop_duplicates().itertuples(index=False)]


def choose_trajectories(frames: Sequence, n: int) -> list[Key]:
    """Up to ``n`` trajectories present in every frame: one per lobe (ur, br, ul, bl) first, then the rest, sorted."""
    common = set(trajectory_keys(frames[0]))
    for df in frames[1:]:
        common &= set(trajectory_keys(df))
    ordered = sorted(common)
    first = [next(k for k in ordered if k[1] == lobe) for lobe in LOBES if any(k[1] == lobe for k in ordered)]
    rest = [k for k in ordered if k not in first]
    return (first + rest)[:n]


def poses(df, key: Key, which: str) -> np.ndarray:
    """``(N, 6)`` absolute poses (``which`` = gt or pred) of one trajectory, in frame order."""
    sel = df[(df["patient"] == key[0]) & (df["lobe"] == key[1]) & (df["trajectory"] == key[2])].sort_values("frame")
    return sel[[f"{which}_abs_{c}" for c in POSE]].to_numpy(dtype=np.float64)


def trajectory_comparison(models: Mapping[str, object], keys: Sequence[Key]):
    """Figure 5: the first model's ground truth vs every model's chained prediction, one 3-D panel per key."""
    first = next(iter(models.values()))
    gt = [poses(first, k, "gt") for k in keys]
    preds = {name: [poses(df, k, "pred") for k in keys] for name, df in models.items()}
    return trajectory_figure(gt, preds, titles=[f"{p} {lobe} trajectory {t}" for p, lobe, t in keys],
                             columns=min(len(keys), 4))


def _errors(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.linalg.norm(pred[:, :3] - gt[:, :3], axis=1), metrics.per_pose_errors(pred, gt)["geodesic"]


def _padded(rows: Sequence[np.ndarray]) -> np.ndarray:
    width = max(len(r) for r in rows)
    return np.array([np.pad(r, (0, width - len(r)), constant_values=np.nan) for r in rows])


def frame_errors(df, which: str = "pred") -> tuple[np.ndarray, np.ndarray]:
    """Accumulated-pose position (voxels) and geodesic (degrees) error per frame, ``(n_traj, max_len)`` NaN-padded,
    of the model (``which="pred"``), the zero-motion reference (``"zero_motion"``: the first pose held) or the
    training-mean reference (``"train_mean"``: its chained poses, ``train_mean_abs_*``)."""
    pos, rot = [], []
    for k in trajectory_keys(df):
        gt = poses(df, k, "gt")
        pred = np.repeat(gt[:1], len(gt), axis=0) if which == REFERENCES[0] else poses(df, k, which)
        p, r = _errors(pred, gt)
        pos.append(p)
        rot.append(r)
    return _padded(pos), _padded(rot)


def reference_errors(df) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The image-blind references' errors per frame on ``df``'s trajectories, by their table row names; the
    training mean only where ``predictions.csv`` has its poses (runs logged before it was written there lack it)."""
    out = {REFERENCE_NAMES[REFERENCES[0]]: frame_errors(df, REFERENCES[0])}
    if all(f"{REFERENCES[1]}_abs_{c}" in df.columns for c in POSE):
        out[REFERENCE_NAMES[REFERENCES[1]]] = frame_errors(df, REFERENCES[1])
    return out


def error_figures(models: Mapping[str, object], caption: str = "") -> dict[str, object]:
    """``{"position": fig, "rotation": fig}``: error of the accumulated pose vs frame, one curve per model and a
    dashed line per image-blind reference (on the first model's trajectories), ``caption`` under the axes."""
    errors = {name: frame_errors(df) for name, df in models.items()}
    refs = reference_errors(next(iter(models.values()))) if models else {}
    title = "personalized: mean ± std over test trajectories"
    labels = {"position": "accumulated position error (voxels)", "rotation": "accumulated rotation error (degrees)"}
    return {kind: error_curve_figure({n: e[k] for n, e in errors.items()}, label, title,
                                     references={n: e[k] for n, e in refs.items()}, caption=caption)
            for k, (kind, label) in enumerate(labels.items())}


def figure_models(index: RunIndex) -> dict[tuple[str, str], str]:
    """(arch, rot_loss) -> which table it comes from, for the error-vs-frame figures: every model of Table 7 (each
    architecture with MSE+CE) and of Table 6 (BronchoTrack, or the sota stage's selection, and OffsetNet with its
    own loss), in the tables' row order."""
    planned = index.expected("ablation", "personalized", index.pose_frame, index.train_size)
    cells = {(i[0], i[1]) for i in planned} if planned is not None else {
        (a, ABLATION_LOSS) for a in arch_names() if index.select("personalized", a, ABLATION_LOSS)}
    out = {(a, ABLATION_LOSS): "Table 7" for a in arch_names() if (a, ABLATION_LOSS) in cells}
    arch, loss, _ = bronchotrack(index)
    for combo in ((arch, loss), OFFSETNET):
        out[combo] = "Tables 6 and 7" if combo in out else "Table 6"
    return out


def _first_run(index: RunIndex, arch: str, loss: str) -> RunRecord | None:
    runs = index.select("personalized", arch, loss)
    return runs[0] if runs else None


def _cached(load: Loader, cache: dict[str, object]) -> Loader:
    def cached(run: RunRecord):
        if run.run_id not in cache:
            cache[run.run_id] = load(run)
        return cache[run.run_id]
    return cached


def _error_figures(index: RunIndex, load: Loader, out: Path, warnings: list[str]) -> list[Path]:
    """fig-error-position / fig-error-rotation: every model of ``figure_models`` (one run each, its lowest seed) and
    the references; the caption names the seeds shown and every model left out, and why."""
    shown, left = {}, []
    seeds = set()
    for (arch, loss), where in figure_models(index).items():
        run = _first_run(index, arch, loss)
        df = load(run) if run is not None else None
        if df is None:
            name = run.model if run is not None else registry.model_name(arch, loss)
            left.append(f"{name} ({where}: {'no predictions.csv' if run else 'no FINISHED personalized run'})")
            continue
        shown[run.model] = df
        seeds.add(run.tag("seed"))
    if not shown:
        warnings.append("figures: no error-vs-frame curves (no personalized run of Table 6 or 7 with predictions.csv)")
        return []
    refs = reference_errors(next(iter(shown.values())))
    missing = [n for r, n in REFERENCE_NAMES.items() if n not in refs]
    caption = (f"Every model of Tables 6 and 7, one run each (seed {', '.join(sorted(seeds))}), and the image-blind "
               f"references (dashed) on the first model's test trajectories.")
    if left:
        caption += f" Left out: {'; '.join(left)}."
        warnings.append(f"figures: the error-vs-frame curves leave out {'; '.join(left)}")
    if missing:
        caption += (f" {' and '.join(missing)} not drawn: its poses are not in these runs' predictions.csv "
                    f"(logged before it was).")
    files: list[Path] = []
    for kind, fig in error_figures(shown, caption).items():
        files += save_figure(fig, out / f"fig-error-{kind}", FORMATS)
    return files


def make_figures(index: RunIndex, load: Loader, out: Path, n_trajectories: int, warnings: list[str]) -> list[Path]:
    """Write the trajectory comparison and the error curves under ``out``; returns the files written."""
    written: list[Path] = []
    cache: dict[str, object] = {}
    load = _cached(load, cache)
    arch, loss, _ = bronchotrack(index)
    runs = {combo: _first_run(index, *combo) for combo in ((arch, loss), OFFSETNET)}
    chosen = {(r.model if r is not None else registry.model_name(*combo)): r for combo, r in runs.items()}
    models = {name: df for name, run in chosen.items() if run is not None and (df := load(run)) is not None}
    for name in chosen.keys() - models.keys():
        warnings.append(f"figures: fig5-trajectories has no {name} curve (no FINISHED personalized run with "
                        f"predictions.csv)")
    if models:
        keys = choose_trajectories(list(models.values()), n_trajectories)
        if keys:
            written += save_figure(trajectory_comparison(models, keys), out / "fig5-trajectories", FORMATS)
        else:
            warnings.append("figures: fig5-trajectories skipped: the runs share no test trajectory")
    written += _error_figures(index, load, out, warnings)
    return written
