"""Read a dataset from disk into validated trajectories and one frames table.

Two layouts are read into the same ``Dataset``:

* ``bronchopose`` (docs/dataset-format.md): ``<root>/dataset.json`` and one
  ``<patient>.csv`` per patient, read by :func:`open_dataset_dir`;
* ``csv``: any per-frame pose CSV(s) with a column mapping, read by
  :mod:`bronchocli.data.importer` (``dataset.format: csv``).

Both go through :func:`assemble`, which checks what training relies on (finite
poses within their bounds, unique frame numbers, at least two frames per trajectory, every frame
file present) and raises ``DataError`` naming the file and line of the first
bad row. Frames are sorted by patient, lobe, trajectory and frame; the row
number of that table is the *global frame index* the frame cache uses, so the
frames of one trajectory are contiguous.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .. import geometry, pathcheck
from ..cells import LOBES
from ..errors import DataError
from .naming import DATASET_JSON

log = logging.getLogger(__name__)
_warned: set[str] = set()  # warnings already given by this process (a dataset is opened many times)
EDIT_SLACK_NS = 2_000_000_000  # a CSV this much newer than dataset.json was edited after generation (not copied)


def warn_once(text: str) -> None:
    """A degradation the user must hear about, once per process (stderr, or the sweep worker's log)."""
    if text not in _warned:
        _warned.add(text)
        log.warning("warning: %s", text)

POSE_COLUMNS: tuple[str, ...] = ("x", "y", "z", "rx", "ry", "rz")  # names in Dataset.frames
DISK_POSE_COLUMNS: tuple[str, ...] = ("pos_x", "pos_y", "pos_z", "Rx", "Ry", "Rz")  # names in <patient>.csv
CSV_COLUMNS: tuple[str, ...] = ("patient", "lobe", "trajectory", "frame", *DISK_POSE_COLUMNS, "filename")
FRAME_COLUMNS: tuple[str, ...] = ("patient", "lobe", "trajectory", "frame", *POSE_COLUMNS, "filename", "path")


@dataclass(frozen=True, eq=False)
class Trajectory:
    """One camera path: absolute poses and the global indices of its frames."""

    patient: str
    lobe: str
    traj_id: str  # as written in the CSV ("3"); unique within (patient, lobe)
    poses: np.ndarray  # (N, 6) float64: voxels, intrinsic XYZ Euler degrees
    frame_index: np.ndarray  # (N,) int64 global frame indices (rows of Dataset.frames)
    filenames: tuple[str, ...]  # absolute frame paths

    @property
    def key(self) -> str:
        """Stable id ``patient/lobe/traj_id``, e.g. ``p00/ur/3``."""
        return f"{self.patient}/{self.lobe}/{self.traj_id}"

    @property
    def n_frames(self) -> int:
        return len(self.frame_index)

    @property
    def n_pairs(self) -> int:
        return len(self.frame_index) - 1

    def __repr__(self) -> str:
        return f"Trajectory({self.key}, {self.n_frames} frames)"


@dataclass(eq=False)
class Dataset:
    """A validated dataset: trajectories, the frames table and the metadata training needs."""

    root: Path
    format: str  # 'bronchopose' or 'csv'
    patients: list[str]
    lobes: list[str]
    frame_shape: tuple[int, int]  # (height, width) of the frames on disk
    fingerprint: str
    frames: pd.DataFrame  # one row per frame (FRAME_COLUMNS); the index is the global frame index
    trajectories: list[Trajectory]
    spacing: dict[str, tuple[float, float, float]]  # patient -> voxel size in mm
    meta: dict[str, Any] = field(default_factory=dict)  # dataset.json (or what the importer knows)
    has_frames: bool = True  # False: an imported poses-only dataset (trajectories to evaluate, nothing to train on)

    @property
    def image_size(self) -> int | None:
        """Side of the square frames on disk; None when they are not square (see ``frame_shape``)."""
        h, w = self.frame_shape
        return h if h == w else None

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    def spacing_mm(self, patient: str) -> np.ndarray:
        """Voxel size of ``patient`` in mm, shape (3,)."""
        if patient not in self.spacing:
            raise DataError(f"{self.root}: no voxel spacing for patient {patient!r} (patients: {', '.join(self.patients)})")
        return np.asarray(self.spacing[patient], dtype=np.float64)

    @cached_property
    def by_key(self) -> dict[str, Trajectory]:
        return {t.key: t for t in self.trajectories}

    def trajectory(self, key: str) -> Trajectory:
        try:
            return self.by_key[key]
        except KeyError:
            raise DataError(f"{self.root}: no trajectory {key!r}") from None

    def of(self, patient: str | None = None, lobe: str | None = None) -> list[Trajectory]:
        """Trajectories of one patient and/or lobe, in dataset order."""
        return [t for t in self.trajectories
                if (patient is None or t.patient == patient) and (lobe is None or t.lobe == lobe)]

    def __repr__(self) -> str:
        return (f"Dataset({self.root}, {self.format}, {len(self.patients)} patients, "
                f"{len(self.trajectories)} trajectories, {self.n_frames} frames)")


# -- ordering -------------------------------------------------------------------


def natural_key(text: str) -> tuple:
    """Sort key that puts "2" before "10" (numeric ids compare as numbers)."""
    try:
        return (0, float(text), text)
    except ValueError:
        return (1, 0.0, text)


def lobe_order(lobes: Iterable[str]) -> list[str]:
    """The paper's lobe order (ur, br, ul, bl) first, any other lobe names after, sorted."""
    lobes = set(lobes)
    return [lb for lb in LOBES if lb in lobes] + sorted(lobes - set(LOBES), key=natural_key)


# -- assembling and validating ----------------------------------------------------


def _where(table: pd.DataFrame, i: int) -> str:
    return f"{table['source'].iat[i]} line {table['line'].iat[i]}"


# What a pose value may be: beyond these it is a corrupt file (1e308 overflows every difference taken from it),
# not a camera. Positions are voxels (a CT volume is < 1e4 voxels a side); angles are Euler degrees, which a
# file may write unwrapped, so two full turns either way are allowed.
MAX_POSITION = 1e6  # |x|, |y|, |z| in voxels
MAX_ANGLE = 720.0  # |rx|, |ry|, |rz| in degrees


def _check_poses(table: pd.DataFrame) -> None:
    """Every pose value finite and within its bound (``MAX_POSITION``, ``MAX_ANGLE``): DataError naming the file,
    line, column and value of the first bad one otherwise."""
    values = table[list(POSE_COLUMNS)].to_numpy(np.float64)
    limit = np.array([MAX_POSITION] * 3 + [MAX_ANGLE] * 3)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(values) | (np.abs(values) > limit)
    if bad.any():
        rows = np.flatnonzero(bad.any(1))
        i = int(min(rows, key=lambda k: (table["source"].iat[k], table["line"].iat[k])))  # first in file order
        j = int(np.flatnonzero(bad[i])[0])
        more = f" ({len(rows) - 1} more rows)" if len(rows) > 1 else ""
        what = "non-finite" if not np.isfinite(values[i, j]) else "out-of-range"
        rule = f"positions within ±{MAX_POSITION:,.0f} voxels" if j < 3 else f"angles within ±{MAX_ANGLE:g}°"
        raise DataError(f"{_where(table, i)}: {what} pose value {POSE_COLUMNS[j]}={values[i, j]:g} (allowed: "
                        f"finite, {rule}){more}")


def _sort(table: pd.DataFrame, patients: Sequence[str]) -> pd.DataFrame:
    rank_p = {p: i for i, p in enumerate(patients)}
    rank_l = {lb: i for i, lb in enumerate(lobe_order(table["lobe"].unique()))}
    rank_t = {t: i for i, t in enumerate(sorted(table["trajectory"].unique(), key=natural_key))}
    keys = pd.DataFrame({
        "p": table["patient"].map(rank_p), "l": table["lobe"].map(rank_l),
        "t": table["trajectory"].map(rank_t), "f": table["frame"],
    })
    order = np.lexsort((keys["f"].to_numpy(), keys["t"].to_numpy(), keys["l"].to_numpy(), keys["p"].to_numpy()))
    return table.iloc[order].reset_index(drop=True)


def _group_starts(table: pd.DataFrame) -> np.ndarray:
    """Row where each (patient, lobe, trajectory) group starts, plus the end (sorted table)."""
    cols = [table[c].to_numpy() for c in ("patient", "lobe", "trajectory")]
    change = np.zeros(len(table), dtype=bool)
    change[0] = True
    for c in cols:
        change[1:] |= c[1:] != c[:-1]
    return np.append(np.flatnonzero(change), len(table))


def _check_groups(table: pd.DataFrame, starts: np.ndarray) -> None:
    frames = table["frame"].to_numpy()
    dup = np.flatnonzero(frames[1:] == frames[:-1]) + 1
    dup = dup[~np.isin(dup, starts)]
    if len(dup):
        i = int(dup[0])
        raise DataError(f"{_where(table, i)}: frame {frames[i]} appears twice in trajectory {_key(table, i)}")
    lengths = np.diff(starts)
    short = np.flatnonzero(lengths < 2)
    if len(short):
        i = int(starts[short[0]])
        raise DataError(f"{_where(table, i)}: trajectory {_key(table, i)} has {lengths[short[0]]} frame "
                        f"(at least 2 are needed for a relative pose){_more(len(short))}")


def _key(table: pd.DataFrame, i: int) -> str:
    return f"{table['patient'].iat[i]}/{table['lobe'].iat[i]}/{table['trajectory'].iat[i]}"


def _more(n: int) -> str:
    return f" ({n - 1} more)" if n > 1 else ""


def _check_files(table: pd.DataFrame) -> None:
    """Every frame file exists (one directory listing per folder, not one stat per frame)."""
    paths = table["path"].tolist()
    existing: set[str] = set()
    for d in {p.rpartition(os.sep)[0] for p in paths}:
        try:
            existing.update(d + os.sep + e.name for e in os.scandir(d or os.sep))
        except (FileNotFoundError, NotADirectoryError):
            pass
    missing = [i for i, p in enumerate(paths) if p not in existing]
    if missing:  # report the first in file order, not in sorted order
        i = min(missing, key=lambda k: (table["source"].iat[k], table["line"].iat[k]))
        raise DataError(f"{_where(table, i)}: frame file {table['filename'].iat[i]!r} not found "
                        f"(looked for {paths[i]}){_more(len(missing))}")


_NOT_NORMAL = re.compile(r"(^|[/\\])\.{1,2}([/\\]|$)|[/\\]{2}|\\")


def join_paths(base: Path, names: pd.Series) -> list[str]:
    """Absolute, normalised frame paths: ``names`` relative to ``base`` (absolute names kept)."""
    base_s = os.path.normpath(os.path.abspath(base))
    out = []
    for n in names.astype(str):
        if os.path.isabs(n):
            out.append(os.path.normpath(n))
        elif _NOT_NORMAL.search(n):  # '.', '..', '//' or backslashes: rare, and normpath is slow at 842k frames
            out.append(os.path.normpath(os.path.join(base_s, n)))
        else:
            out.append(base_s + os.sep + n)
    return out


def assemble(table: pd.DataFrame, patients: Sequence[str] | None = None,
             check_files: bool = True) -> tuple[pd.DataFrame, list[Trajectory]]:
    """Validate a normalised frames table and cut it into trajectories.

    ``table`` has FRAME_COLUMNS plus ``source`` (file) and ``line`` (1-based
    line in that file) for error messages. Returns the sorted frames table
    (index = global frame index) and the trajectories in the same order.
    """
    if table.empty:
        raise DataError(f"{', '.join(sorted(set(table['source'])) or ['dataset'])}: no frames")
    patients = list(patients) if patients is not None else sorted(table["patient"].unique(), key=natural_key)
    _check_poses(table)
    table = _sort(table, patients)
    starts = _group_starts(table)
    _check_groups(table, starts)
    if check_files:
        _check_files(table)
    poses = table[list(POSE_COLUMNS)].to_numpy(np.float64, copy=True)
    # One XYZ triple per rotation (beta in [-90, 90]), whatever form the file wrote: canonical ones stay bit for
    # bit, the others' world-frame labels would otherwise jump by ~180° (geometry.canonical_euler).
    poses[:, 3:] = geometry.canonical_euler(poses[:, 3:])
    table = table.assign(**{c: poses[:, 3 + i] for i, c in enumerate(POSE_COLUMNS[3:])})
    paths = table["path"].to_numpy()
    ids = {c: table[c].to_numpy(object)[starts[:-1]] for c in ("patient", "lobe", "trajectory")}
    trajectories = []
    for k, (a, b) in enumerate(zip(starts[:-1], starts[1:])):
        trajectories.append(Trajectory(
            patient=str(ids["patient"][k]), lobe=str(ids["lobe"][k]), traj_id=str(ids["trajectory"][k]),
            poses=poses[a:b].copy(), frame_index=np.arange(a, b, dtype=np.int64), filenames=tuple(paths[a:b]),
        ))
    return table[list(FRAME_COLUMNS)], trajectories


# -- fingerprint --------------------------------------------------------------------


def stat_fingerprint(parts: Iterable[bytes], frame_paths: Iterable[str], root: Path) -> str:
    """sha256 of ``parts`` (e.g. CSV bytes, import settings) and each frame's relative path, size and mtime.

    Used when no content fingerprint is recorded (foreign CSV datasets): cheap
    (no frame is read) and it changes whenever a CSV or any frame file does.
    """
    h = hashlib.sha256()
    for part in parts:
        h.update(hashlib.sha256(part).digest())
    for p in sorted(frame_paths):
        st = os.stat(p)
        rel = os.path.relpath(p, root) if os.path.isabs(p) else p
        h.update(f"{rel}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


# -- the project's own layout ----------------------------------------------------------


def _read_meta(root: Path) -> dict[str, Any]:
    path = root / DATASET_JSON
    if not root.is_dir():
        raise DataError(f"{root}: dataset directory not found")
    if not _read_file(path, "dataset file").is_file():
        raise DataError(f"{path}: not found (an incomplete generation, or not a bronchopose dataset: "
                        "for a foreign CSV set dataset.format: csv)")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise DataError(f"{path}: expected a JSON object")
    missing = [k for k in ("patients", "image_size", "voxel_grid") if k not in meta]
    if missing:
        raise DataError(f"{path}: missing key(s) {', '.join(missing)}")
    if not isinstance(meta["patients"], list) or not meta["patients"]:
        raise DataError(f"{path}: 'patients' must be a non-empty list")
    return meta


def _spacing(meta: dict[str, Any], path: Path) -> dict[str, tuple[float, float, float]]:
    out = {}
    for p in meta["patients"]:
        try:
            s = tuple(float(v) for v in meta["voxel_grid"][p]["spacing_mm"])
        except (KeyError, TypeError, ValueError):
            raise DataError(f"{path}: voxel_grid.{p}.spacing_mm missing or not three numbers") from None
        if len(s) != 3 or not all(np.isfinite(s)) or min(s) <= 0:
            raise DataError(f"{path}: voxel_grid.{p}.spacing_mm must be three positive numbers, got {list(s)}")
        out[p] = s
    return out


def _frame_shape(meta: dict[str, Any], path: Path) -> tuple[int, int]:
    size = meta["image_size"]
    if isinstance(size, int):
        return size, size
    if isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size):
        return size[1], size[0]  # dataset.json stores [width, height]
    raise DataError(f"{path}: image_size must be [width, height] in pixels, got {size!r}")


def read_patient_csv(root: Path, patient: str) -> pd.DataFrame:
    """``<root>/<patient>.csv`` -> normalised frames table (with source/line for errors)."""
    path = _read_file(root / f"{patient}.csv", "patient file")
    if not path.is_file():
        raise DataError(f"{path}: not found ({DATASET_JSON} lists patient {patient!r})")
    try:
        raw = pd.read_csv(path, dtype={"patient": str, "lobe": str, "trajectory": str, "filename": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not a readable CSV ({str(exc).splitlines()[0]})") from None
    missing = [c for c in CSV_COLUMNS if c not in raw.columns]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)} (found: {', '.join(map(str, raw.columns))})")
    if raw.empty:
        raise DataError(f"{path}: no frames ({DATASET_JSON} lists patient {patient!r})")
    table = pd.DataFrame({
        "patient": raw["patient"], "lobe": raw["lobe"], "trajectory": raw["trajectory"],
        **{ours: pd.to_numeric(raw[disk], errors="coerce") for ours, disk in zip(POSE_COLUMNS, DISK_POSE_COLUMNS)},
        "filename": raw["filename"],
    })
    table.insert(3, "frame", integer_column(raw["frame"], "frame", path))
    table["source"], table["line"] = str(path), np.arange(len(raw)) + 2  # line 1 is the header
    _check_text(table, ("patient", "lobe", "trajectory", "filename"), path)
    _check_row_names(table, ("lobe", "trajectory"), path)
    wrong = np.flatnonzero(table["patient"].to_numpy() != patient)
    if len(wrong):
        raise DataError(f"{path} line {wrong[0] + 2}: patient {table['patient'].iat[wrong[0]]!r}, expected {patient!r}")
    table["path"] = join_paths(root, table["filename"])
    check_inside(table, root, "the dataset folder")
    return table


def check_inside(table: pd.DataFrame, folder: Path, name: str) -> None:
    """Every frame path stays inside ``folder``: a ``filename`` that leaves it (``../x``, an absolute path) is
    refused, naming the row (a dataset reads only its own files)."""
    bad = pathcheck.outside(folder, table["path"].tolist())
    if bad:
        i = min(bad, key=lambda k: (table["source"].iat[k], table["line"].iat[k]))
        raise DataError(f"{_where(table, i)}: frame file {table['filename'].iat[i]!r} is outside {name} {folder}; "
                        f"a filename must be a path inside it, without '..'{_more(len(bad))}")


def integer_column(values: pd.Series, name: str, path: Path) -> pd.Series:
    """A column of whole numbers, or DataError naming the first bad line."""
    num = pd.to_numeric(values, errors="coerce").to_numpy(np.float64)
    bad = np.flatnonzero(~np.isfinite(num) | (num != np.round(num)))
    if len(bad):
        raise DataError(f"{path} line {bad[0] + 2}: {name} must be a whole number, got {values.iat[bad[0]]!r}")
    return pd.Series(num.astype(np.int64), index=values.index)


def _check_text(table: pd.DataFrame, columns: Sequence[str], path: Path) -> None:
    for c in columns:
        bad = np.flatnonzero(table[c].isna().to_numpy())
        if len(bad):
            raise DataError(f"{path} line {bad[0] + 2}: empty {c}")


def _fingerprint(root: Path, meta: dict[str, Any], csvs: dict[str, bytes], frame_paths: pd.Series) -> str:
    """dataset.json's content fingerprint, unless a CSV changed after it was written: then one over the current
    CSVs too (with a warning), so runs and caches never take edited data for the data that was generated."""
    recorded = meta.get("fingerprint")
    if not recorded:
        return stat_fingerprint(list(csvs.values()), frame_paths, root)
    hashes = meta.get("csv_sha256")
    if isinstance(hashes, dict):
        edited = [p for p, data in csvs.items() if hashlib.sha256(data).hexdigest() != hashes.get(p)]
    else:  # written before dataset.json recorded its CSVs' hashes: a CSV clearly newer than it was edited
        written = (root / DATASET_JSON).stat().st_mtime_ns
        edited = [p for p in csvs if (root / f"{p}.csv").stat().st_mtime_ns > written + EDIT_SLACK_NS]
    if not edited:
        return str(recorded)
    warn_once(f"dataset {root}: {', '.join(f'{p}.csv' for p in edited)} changed after dataset.json was written; "
              "its recorded fingerprint no longer covers the data, so a fingerprint of the current contents is used")
    h = hashlib.sha256(str(recorded).encode())
    for p in sorted(csvs):
        h.update(hashlib.sha256(csvs[p]).digest())
    return h.hexdigest()


def _warn_empty_lobes(root: Path, patients: Sequence[str], lobes: Sequence[str], frames: pd.DataFrame) -> None:
    """Warn about each (patient, lobe) of the dataset that holds no trajectory: it trains and tests without it."""
    present = set(zip(frames["patient"].astype(str), frames["lobe"].astype(str)))
    empty = [f"{p}/{lb}" for p in patients for lb in lobes if (str(p), str(lb)) not in present]
    if empty:
        warn_once(f"dataset {root}: no trajectories in {', '.join(empty)} (lobes {', '.join(lobes)} are listed); "
                  "training, validation and test go on without them")


def _check_names(path: Path, key: str, names: Sequence[str], why: str) -> None:
    """Every name of ``path``'s ``key`` list a plain file name (``pathcheck.plain_name``): one line otherwise."""
    for i, name in enumerate(names):
        if not pathcheck.plain_name(name):
            raise DataError(f"{path}: {key}[{i}] {name!r}: {why} (no '/', '\\' or '..')")


def _check_row_names(table: pd.DataFrame, columns: Sequence[str], path: Path) -> None:
    """The lobe and trajectory of every row plain names (they name folders: ``<patient>/<lobe>/<trajectory>``)."""
    for c in columns:
        values = table[c].astype(str)
        bad = [v for v in values.unique() if not pathcheck.plain_name(v)]
        if bad:
            row = int(np.flatnonzero(values.isin(bad).to_numpy())[0])
            raise DataError(f"{path} line {row + 2}: {c} {values.iat[row]!r}: a {c} is a folder name in the "
                            "dataset (no '/', '\\' or '..')")


def _read_file(path: Path, what: str) -> Path:
    """``path`` if it is a file; a symbolic link loop there is one line saying so (``is_file`` alone says no)."""
    pathcheck.resolve(path, what)
    return path


def open_dataset_dir(root: str | os.PathLike) -> Dataset:
    """Read a dataset in the project's layout (``dataset.json`` + one CSV per patient)."""
    root = pathcheck.resolve(root, "dataset")
    meta = _read_meta(root)
    meta_path = root / DATASET_JSON
    patients = [str(p) for p in meta["patients"]]
    _check_names(meta_path, "patients", patients, "a patient name is a file name in the dataset folder")
    table = pd.concat([read_patient_csv(root, p) for p in patients], ignore_index=True)
    frames, trajectories = assemble(table, patients)
    csvs = {p: (root / f"{p}.csv").read_bytes() for p in patients}
    fingerprint = _fingerprint(root, meta, csvs, frames["path"])
    lobes = [str(lb) for lb in meta.get("lobes") or lobe_order(frames["lobe"].unique())]
    _check_names(meta_path, "lobes", lobes, "a lobe name is a folder name in the dataset (<patient>/<lobe>/...)")
    _warn_empty_lobes(root, patients, lobes, frames)
    return Dataset(root=root, format="bronchopose", patients=patients, lobes=lobes,
                   frame_shape=_frame_shape(meta, meta_path), fingerprint=str(fingerprint), frames=frames,
                   trajectories=trajectories, spacing=_spacing(meta, meta_path), meta=meta)
