"""Import a foreign pose dataset: per-frame pose CSV(s) plus image files (``dataset.format: csv``).

``dataset.csv`` in experiments.yaml says which columns hold what, the angle
units and Euler convention, and whether positions are in voxels or mm, so a
CSV with e.g. ``X, Y, Z, Roll, Pitch, Yaw`` in degrees and positions in mm
trains without converting by hand. Every row is converted to the project's
convention (positions in voxels, intrinsic X-Y-Z Euler angles in degrees, see
bronchocli.geometry; always the canonical triple of each rotation, beta in
[-90, 90], whichever of its two triples the file holds) and then validated
like a generated dataset. Trajectories whose world-frame labels are not their
motion (near gimbal lock, gimbal.py) are named in a warning.

The fingerprint of an imported dataset (it keys the frame cache) is the
sha256 of the import settings, the CSV bytes, and each frame's relative path,
size and modification time: editing a CSV, a setting or any frame file gives
a new fingerprint without reading every image.
"""

from __future__ import annotations

import glob
import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image
from scipy.spatial.transform import Rotation

from .. import geometry, pathcheck
from ..config import CsvImport
from ..errors import DataError
from .gimbal import world_label_warning
from .naming import file_patient_id
from .reader import (
    POSE_COLUMNS,
    Dataset,
    assemble,
    check_inside,
    integer_column,
    join_paths,
    lobe_order,
    natural_key,
    stat_fingerprint,
    warn_once,
)

SINGLE_LOBE = "all"  # lobe name when dataset.csv.columns.lobe is null
SINGLE_TRAJECTORY = "0"  # trajectory id when dataset.csv.columns.trajectory is null


def csv_files(root: Path, cfg: CsvImport) -> list[Path]:
    """The CSVs to import: ``dataset.csv.files`` (paths or globs relative to the root), default ``*.csv``."""
    if not root.is_dir():
        raise DataError(f"{root}: dataset directory not found")
    patterns = cfg.files or ["*.csv"]
    found: list[Path] = []
    for pattern in patterns:
        hits = sorted(glob.glob(os.path.join(root, pattern)))
        if not hits:
            raise DataError(f"dataset.csv.files: {pattern!r} matches no file in {root}")
        outside = pathcheck.outside(root, [os.path.normpath(h) for h in hits])
        if outside:
            raise DataError(f"dataset.csv.files: {pattern!r} matches {hits[outside[0]]}, outside the dataset folder "
                            f"{root}; list CSVs inside it")
        found += [pathcheck.resolve(h, "dataset.csv.files") for h in hits
                  if pathcheck.resolve(h, "dataset.csv.files") not in found]
    return found


def _read(path: Path, cfg: CsvImport) -> pd.DataFrame:
    cols = cfg.columns
    text_cols = [c for c in (cols.patient, cols.lobe, cols.trajectory, cols.filename) if c]
    try:
        raw = pd.read_csv(path, dtype={c: str for c in text_cols})
    except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as exc:
        raise DataError(f"{path}: not a readable CSV ({str(exc).splitlines()[0]})") from None
    wanted = {k: v for k, v in cols.model_dump().items() if v is not None}
    missing = [f"{v!r} (dataset.csv.columns.{k})" for k, v in wanted.items() if v not in raw.columns]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}; found: {', '.join(map(str, raw.columns))}")
    if raw.empty:
        raise DataError(f"{path}: no rows")
    return raw


def _finite(raw: pd.DataFrame, names: list[str], path: Path) -> np.ndarray:
    values = np.column_stack([pd.to_numeric(raw[n], errors="coerce").to_numpy(np.float64) for n in names])
    bad = ~np.isfinite(values)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        value = raw[names[j]].iat[i]
        shown = repr(value) if isinstance(value, str) else str(value)
        raise DataError(f"{path} line {i + 2}: non-finite or non-numeric pose value in column {names[j]!r}: {shown}")
    return values


def _axis(name: str) -> np.ndarray:
    v = np.zeros(3)
    v["xyz".index(name[-1])] = -1.0 if name.startswith("-") else 1.0
    return v


def camera_axes(forward: str, up: str) -> np.ndarray:
    """``P``: our camera axes (x forward, y left, z up) as columns, in the imported camera's frame.

    An imported orientation ``R_imp`` (columns: the imported camera's axes in the
    world) becomes ours as ``R_imp @ P``; P is a rotation (y = z × x keeps it right-handed).
    """
    f, u = _axis(forward), _axis(up)
    return np.column_stack([f, np.cross(u, f), u])


def convert_angles(angles: np.ndarray, cfg: CsvImport) -> np.ndarray:
    """Angles ``(N, 3)`` in ``cfg.euler`` / ``cfg.angle_units`` of a camera whose axes are
    ``cfg.camera_forward`` / ``cfg.camera_up`` -> our camera's intrinsic XYZ Euler degrees, canonical.

    Always through the rotation matrix, even when the file already uses our convention: every rotation has
    two XYZ triples, (a, b, c) and (a+180, 180-b, c+180), and a file may hold either (or switch between them
    from frame to frame). The matrix and back (geometry.canonical_euler) gives the one triple that chaining also returns (beta in
    [-90, 90], geometry.canonical_euler), so world-frame labels and Euler metrics compare rotations.
    """
    degrees = cfg.angle_units == "deg"
    same_axes = (cfg.camera_forward, cfg.camera_up) == ("x", "z")
    if cfg.euler == "XYZ" and same_axes:  # our convention: canonical triples stay exactly as written
        return geometry.canonical_euler(angles if degrees else np.degrees(angles))
    matrices = Rotation.from_euler(cfg.euler, angles, degrees=degrees).as_matrix()
    if not same_axes:
        matrices = matrices @ camera_axes(cfg.camera_forward, cfg.camera_up)
    return geometry.matrix_to_euler(matrices)


def convert_positions(positions: np.ndarray, cfg: CsvImport) -> np.ndarray:
    """Positions ``(N, 3)`` -> voxels (mm are divided by ``cfg.spacing_mm``)."""
    if cfg.position_units == "mm":
        return positions / np.asarray(cfg.spacing_mm, dtype=np.float64)
    return positions


def _ids(raw: pd.DataFrame, column: str | None, default: str, path: Path, name: str) -> pd.Series:
    if column is None:
        return pd.Series([default] * len(raw), index=raw.index)
    values = raw[column]
    bad = np.flatnonzero(values.isna().to_numpy())
    if len(bad):
        raise DataError(f"{path} line {bad[0] + 2}: empty {name} (column {column!r})")
    return values.astype(str).str.strip()


def read_table(path: Path, root: Path, cfg: CsvImport) -> pd.DataFrame:
    """One foreign CSV -> the normalised frames table :func:`reader.assemble` validates."""
    raw = _read(path, cfg)
    c = cfg.columns
    table = pd.DataFrame({
        "patient": _ids(raw, c.patient, file_patient_id(path.stem), path, "patient"),
        "lobe": _ids(raw, c.lobe, SINGLE_LOBE, path, "lobe"),
        "trajectory": _ids(raw, c.trajectory, SINGLE_TRAJECTORY, path, "trajectory"),
    })
    if c.frame is None:  # row order within each trajectory
        table["frame"] = table.groupby(["patient", "lobe", "trajectory"], sort=False).cumcount().astype(np.int64)
    else:
        table["frame"] = integer_column(raw[c.frame], "frame", path)
    pos = convert_positions(_finite(raw, [c.x, c.y, c.z], path), cfg)
    ang = convert_angles(_finite(raw, [c.rx, c.ry, c.rz], path), cfg)
    for name, values in zip(POSE_COLUMNS, np.column_stack([pos, ang]).T):
        table[name] = values
    if c.filename is None:  # poses only: no frame files
        table["filename"] = table["path"] = ""
    else:
        table["filename"] = _ids(raw, c.filename, "", path, "filename")
        frames = pathcheck.resolve(root / cfg.frames, "dataset.csv.frames")
        table["path"] = join_paths(frames, table["filename"])
    table["source"], table["line"] = str(path), np.arange(len(raw)) + 2  # line 1 is the header
    if c.filename is not None:
        check_inside(table, frames, "the frames folder (dataset.csv.frames)")
    return table


def _frame_shape(path: str) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.height, im.width
    except OSError as exc:
        raise DataError(f"{path}: not a readable image ({exc})") from None


def csv_patients(root: Path, cfg: CsvImport) -> list[str]:
    """Patient ids of a foreign dataset, reading only the patient column (cheap)."""
    out: set[str] = set()
    for path in csv_files(root, cfg):
        if cfg.columns.patient is None:
            out.add(file_patient_id(path.stem))
        else:
            col = _read(path, cfg)[cfg.columns.patient].dropna().astype(str).str.strip()
            out.update(col.unique())
    return sorted(out, key=natural_key)


def import_csv(root: str | os.PathLike, cfg: CsvImport) -> Dataset:
    """Read a foreign pose dataset under ``root`` as configured by ``dataset.csv``."""
    root = pathcheck.resolve(root, "dataset")
    files = csv_files(root, cfg)
    table = pd.concat([read_table(f, root, cfg) for f in files], ignore_index=True)
    patients = sorted(table["patient"].unique(), key=natural_key)
    has_frames = cfg.columns.filename is not None
    frames, trajectories = assemble(table, patients, check_files=has_frames)
    settings = json.dumps(cfg.model_dump(mode="json"), sort_keys=True).encode()
    fingerprint = stat_fingerprint([settings, *(f.read_bytes() for f in files)],
                                   frames["path"] if has_frames else [], root)
    meta = {"format": "csv", "files": [str(f) for f in files], "import": cfg.model_dump(mode="json")}
    dataset = Dataset(root=root, format="csv", patients=patients, lobes=lobe_order(frames["lobe"].unique()),
                      frame_shape=_frame_shape(frames["path"].iat[0]) if has_frames else (0, 0),
                      fingerprint=fingerprint, frames=frames, trajectories=trajectories,
                      spacing={p: tuple(cfg.spacing_mm) for p in patients}, meta=meta, has_frames=has_frames)
    gimbal = world_label_warning(dataset)  # foreign trajectories may pass near gimbal lock (gimbal.py)
    if gimbal:
        warn_once(gimbal)
    return dataset
