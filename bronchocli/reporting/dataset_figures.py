"""Figures of a ``bronchopose`` dataset: a montage of sample frames and the 3-D positions visited.

``montage_figure`` shows, for each (patient, lobe), frames sampled evenly
along one trajectory (trachea on the left, distal on the right);
``positions_figure`` is the paper's Figure 1: every camera position of each
patient in voxel coordinates, coloured by lobe, over the patient's centreline
graph. Both return matplotlib figures (Agg) so the report command can reuse
them. The centreline overlay needs VTK (to read ``airway.vtp``); without it the
positions are drawn alone and ``warnings`` says so once.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from ..data.cache import decode_frame
from ..data.naming import DATASET_JSON
from ..data.reader import open_dataset_dir
from ..errors import DataError
from ..io import read_polydata, save_figure

LOBE_COLOURS = {"ur": "tab:red", "br": "tab:purple", "ul": "tab:blue", "bl": "tab:cyan"}
LOBE_NAMES = {"ur": "right upper", "br": "right lower", "ul": "left upper", "bl": "left lower"}


def load_meta(root: Path) -> dict:
    path = Path(root) / DATASET_JSON
    if not path.is_file():
        raise DataError(f"{root}: not a complete bronchopose dataset ({DATASET_JSON} missing)")
    return json.loads(path.read_text())


def load_frames(root: Path, patients: Sequence[str] | None = None) -> pd.DataFrame:
    """The rows of the dataset's patient CSVs (all columns), for the given patients or all."""
    meta = load_meta(root)
    tables = []
    for p in patients or meta["patients"]:
        path = Path(root) / f"{p}.csv"
        if not path.is_file():
            raise DataError(f"{path}: not found ({DATASET_JSON} lists patient {p!r})")
        tables.append(pd.read_csv(path, dtype={"patient": str, "lobe": str}))
    return pd.concat(tables, ignore_index=True)


def _sample_rows(frames: pd.DataFrame, columns: int) -> list[pd.Series]:
    """``columns`` frames evenly spaced along the longest trajectory of a (patient, lobe)."""
    lengths = frames.groupby("trajectory").size()
    traj = frames[frames["trajectory"] == lengths.idxmax()].sort_values("frame")
    idx = np.unique(np.linspace(0, len(traj) - 1, columns).round().astype(int))
    return [traj.iloc[i] for i in idx]


def montage_figure(root: Path, *, columns: int = 6, patients: Sequence[str] | None = None, max_rows: int = 20):
    """One row per (patient, lobe): frames along a trajectory, labelled with frame number and arc length."""

    frames = load_frames(root, patients)
    groups = [g for _, g in frames.groupby(["patient", "lobe"], sort=False)][:max_rows]
    fig, axes = plt.subplots(len(groups), columns, figsize=(1.6 * columns, 1.7 * len(groups)), squeeze=False)
    for r, g in enumerate(groups):
        rows = _sample_rows(g, columns)
        for c, ax in enumerate(axes[r]):
            ax.set_xticks([])
            ax.set_yticks([])
            for s in ax.spines.values():
                s.set_visible(False)
            if c >= len(rows):
                continue
            row = rows[c]
            ax.imshow(decode_frame(str(Path(root) / row["filename"]), None).transpose(1, 2, 0))
            arc = f" {row['arc_mm']:.0f} mm" if "arc_mm" in row else ""
            ax.set_title(f"f{int(row['frame'])}{arc}", fontsize=7, pad=2)
        patient = str(g["patient"].iat[0])
        patient = patient if len(patient) <= 12 else patient[:11] + "…"
        axes[r][0].set_ylabel(f"{patient}\n{g['lobe'].iat[0]}", fontsize=8)
    fig.suptitle("sample frames per patient and lobe, along the trajectory with most frames (frame, arc length)",
                 fontsize=9)
    fig.tight_layout()
    return fig


def _centreline_voxels(root: Path, patient: str, meta: dict, warnings: list[str]) -> list[np.ndarray]:
    """Polylines of the patient's centreline graph in voxels (empty when airway.vtp or VTK is absent)."""
    path = Path(root) / patient / "airway.vtp"
    if not path.is_file():
        return []
    try:
        from vtkmodules.util.numpy_support import vtk_to_numpy  # lazy: VTK is optional outside generation

        poly = read_polydata(path)  # imports VTK's XML reader
    except ImportError:
        note = "figures: VTK is not installed here: the positions figure is drawn without the centreline graph"
        if note not in warnings:
            warnings.append(note)
        return []
    pts = vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    grid = meta["voxel_grid"][patient]
    pts = (pts - np.asarray(grid["origin_mm"])) / np.asarray(grid["spacing_mm"])
    lines = poly.GetLines()
    offsets = vtk_to_numpy(lines.GetOffsetsArray())
    conn = vtk_to_numpy(lines.GetConnectivityArray())
    return [pts[conn[a:b]] for a, b in zip(offsets[:-1], offsets[1:])]


def positions_figure(root: Path, *, patients: Sequence[str] | None = None, max_points: int = 20000,
                     warnings: list[str] | None = None):
    """Camera positions visited per patient (3-D, voxel axes), coloured by lobe, over the centreline graph."""
    warnings = [] if warnings is None else warnings
    meta = load_meta(root)
    patients = list(patients or meta["patients"])
    frames = load_frames(root, patients)
    cols = min(len(patients), 3)
    rows = -(-len(patients) // cols)
    fig = plt.figure(figsize=(4.2 * cols, 4.0 * rows))
    for k, p in enumerate(patients):
        ax = fig.add_subplot(rows, cols, k + 1, projection="3d")
        for line in _centreline_voxels(root, p, meta, warnings):
            ax.plot(line[:, 0], line[:, 1], line[:, 2], color="0.75", lw=0.6)
        sub = frames[frames["patient"] == p]
        step = max(1, len(sub) // max_points)
        for lobe, g in sub.iloc[::step].groupby("lobe", sort=False):
            ax.scatter(g["pos_x"], g["pos_y"], g["pos_z"], s=1.5, color=LOBE_COLOURS.get(lobe),
                       label=LOBE_NAMES.get(lobe, lobe), depthshade=False)
        ax.set_title(p, fontsize=9)
        ax.set_xlabel("x (voxels)", fontsize=7)
        ax.set_ylabel("y (voxels)", fontsize=7)
        ax.set_zlabel("z (voxels)", fontsize=7)
        ax.tick_params(labelsize=6)
        if k == 0:
            ax.legend(fontsize=6, markerscale=4, loc="upper left")
    fig.suptitle("camera positions visited (voxels), by lobe", fontsize=10)
    fig.tight_layout()
    return fig


def preview(root: Path, out: Path, *, columns: int = 6, formats: Sequence[str] = ("png",)) -> list[Path]:
    """Write the montage to ``out`` and the positions plot beside it (``<stem>-positions``).

    The dataset is validated first, as training reads it: a bad row is one DataError naming its file and line.
    """
    out = Path(out)
    open_dataset_dir(root)
    written = save_figure(montage_figure(root, columns=columns), out, formats, dpi=120)
    written += save_figure(positions_figure(root), out.with_name(f"{out.stem}-positions{out.suffix}"), formats,
                           dpi=120)
    return written
