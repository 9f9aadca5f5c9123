"""Writing a ``bronchopose`` dataset: atomic files, frame PNGs, patient CSVs, fingerprint, dataset.json.

Every finished file is written to a temporary name in its own directory and
moved into place with ``os.replace``, so a reader never sees half a frame or
half a CSV. The layout and columns are those of docs/dataset-format.md.

Fingerprint (recorded in dataset.json): SHA-256 over, for each patient in
dataset.json's order, the bytes of ``<patient>.csv`` followed by the 32-byte
SHA-256 digest of every frame file listed in that CSV, in row order. Pose fingerprint (also recorded):
SHA-256 over the patients' CSV bytes alone, in the same order: the same on every host (the poses are
computed with :mod:`bronchocli.hostfree`), while frames also depend on the renderer (docs/reproduction.md).
"""

from __future__ import annotations

import errno
import hashlib
import io as _bytes_io
import os
import shutil
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from .. import geometry, pathcheck
from ..errors import WriteFailed
from ..io import fmt_bytes, write_bytes
from .trajectories import PlannedTrajectory

PNG_COMPRESSION = 1  # zlib level: the fastest level still shrinks frames ~2x (benchmarks/README.md, "Rendering")
CSV_COLUMNS: tuple[str, ...] = (
    "patient", "lobe", "trajectory", "frame", "pos_x", "pos_y", "pos_z", "Rx", "Ry", "Rz", "filename",
    "base_filename", "arc_mm", "dx", "dy", "dz", "roll", "clearance_mm", "radius_mm", "clamped",
)
# free space kept beyond each frame: the digests and the end's CSVs and dataset.json (checked again before them)
FRAME_MARGIN = 256 << 10
FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
FORMAT_NAME = "bronchopose-dataset"
FORMAT_VERSION = 1


# -- frames -----------------------------------------------------------------------------


def encode_png(frame: np.ndarray) -> bytes:
    """An ``H x W x 3`` uint8 frame as PNG bytes (fast compression, deterministic)."""
    buf = _bytes_io.BytesIO()
    Image.fromarray(np.ascontiguousarray(frame), "RGB").save(buf, format="PNG", compress_level=PNG_COMPRESSION)
    return buf.getvalue()


def write_frame(path: Path, frame: np.ndarray, root: Path | None = None) -> bytes:
    """Write one frame atomically after checking the free space (``ensure_room``); returns the SHA-256 digest of
    the file bytes. A full disk is a WriteFailed naming ``root`` (default: the frame's folder); nothing
    half-written is left."""
    data = encode_png(frame)
    where = Path(root) if root is not None else path.parent
    ensure_room(where, len(data) + FRAME_MARGIN)
    try:
        write_bytes(path, data)
    except OSError as exc:
        if exc.errno not in FULL_ERRNOS:
            raise
        raise disk_full(where, len(data) + FRAME_MARGIN, os_error=exc) from None
    return hashlib.sha256(data).digest()


def free_bytes(folder: Path) -> int | None:
    """Free bytes on the file system of ``folder`` (its nearest existing ancestor); None when it cannot tell."""
    try:
        return shutil.disk_usage(pathcheck.nearest_existing(folder)).free
    except OSError:
        return None


def disk_full(folder: Path, need: int, os_error: OSError | None = None) -> WriteFailed:
    """The disk of ``folder`` has less than ``need`` bytes free (or refused a write): one line (the generator
    adds what was kept and what is left)."""
    free = free_bytes(folder)
    why = os.strerror(os_error.errno) if os_error is not None and os_error.errno else "not enough free space"
    return WriteFailed(f"{folder}: disk full ({why}: {fmt_bytes(free) if free is not None else 'unknown'} free on "
                       f"the file system mounted at {pathcheck.mount_point(folder)}, needs at least {fmt_bytes(need)})")


def ensure_room(folder: Path, need: int) -> None:
    """WriteFailed (one line) unless the disk of ``folder`` has ``need`` bytes free: checked before writing, so the
    disk never fills under a writer (VTK's, numpy's, Pillow's) that would crash instead of failing cleanly."""
    free = free_bytes(folder)
    if free is not None and free < need:
        raise disk_full(folder, need)


def file_digest(path: Path) -> bytes:
    return hashlib.sha256(Path(path).read_bytes()).digest()


@dataclass(frozen=True)
class DatasetFrames:
    """The renderer's frame sink for a dataset root: PNG files written atomically, SHA-256 digests."""

    root: str

    def exists(self, name: str) -> bool:
        return (Path(self.root) / name).exists()

    def digest(self, name: str) -> bytes:
        return file_digest(Path(self.root) / name)

    def write(self, name: str, frame: np.ndarray) -> bytes:
        return write_frame(Path(self.root) / name, frame, Path(self.root))


def frame_filename(patient: str, lobe: str, trajectory: int, frame: int) -> str:
    """Frame path relative to the dataset root, e.g. ``p00/ur/t003_f0012.png``."""
    return f"{patient}/{lobe}/t{trajectory:03d}_f{frame:04d}.png"


def base_filename(lobe: str, base_index: int) -> str:
    """Id of the un-varied view at base point ``base_index`` of ``lobe``'s path, e.g. ``ur/b00042``."""
    return f"{lobe}/b{base_index:05d}"


# -- CSV ----------------------------------------------------------------------------------


def _num(x: float) -> str:
    return f"{round(float(x), 6) + 0.0:.6f}"  # + 0.0 turns -0.0 into 0.0


def trajectory_rows(plan: PlannedTrajectory, to_voxels) -> list[str]:
    """CSV lines (no newline) of one planned trajectory; ``to_voxels`` maps mm to voxel coordinates."""
    pos = to_voxels(plan.position_mm)
    euler = geometry.matrix_to_euler(plan.rotation)
    rows = []
    for f in range(len(plan)):
        values = [
            plan.patient, plan.lobe, str(plan.index), str(f),
            *(_num(v) for v in pos[f]), *(_num(v) for v in euler[f]),
            frame_filename(plan.patient, plan.lobe, plan.index, f), base_filename(plan.lobe, int(plan.base_index[f])),
            _num(plan.arc_mm[f]), *(str(int(v)) for v in plan.offset_voxels[f]), _num(plan.roll_deg[f]),
            _num(plan.clearance_mm[f]), _num(plan.radius_mm[f]), str(int(bool(plan.clamped[f]))),
        ]
        rows.append(",".join(values))
    return rows


def patient_csv(plans: Sequence[PlannedTrajectory], to_voxels) -> str:
    """The whole ``<patient>.csv`` text: header and rows ordered by lobe (given order), trajectory, frame."""
    lines = [",".join(CSV_COLUMNS)]
    for plan in plans:
        lines += trajectory_rows(plan, to_voxels)
    return "\n".join(lines) + "\n"


# -- fingerprint and metadata ---------------------------------------------------------------


def fingerprint(parts: Iterable[tuple[bytes, Sequence[bytes]]]) -> str:
    """SHA-256 hex over (CSV bytes, frame digests in row order) per patient, in order."""
    h = hashlib.sha256()
    for csv_bytes, digests in parts:
        h.update(csv_bytes)
        for d in digests:
            h.update(d)
    return h.hexdigest()


def pose_fingerprint(csvs: Iterable[bytes]) -> str:
    """SHA-256 hex over the patients' CSV bytes (poses and trajectory facts), in order."""
    h = hashlib.sha256()
    for data in csvs:
        h.update(data)
    return h.hexdigest()


def fingerprint_dir(root: Path, patients: Sequence[str]) -> str:
    """Recompute the fingerprint of a dataset on disk from its CSVs and frame files."""
    parts = []
    for p in patients:
        data = (Path(root) / f"{p}.csv").read_bytes()
        lines = data.decode("utf-8").splitlines()
        col = lines[0].split(",").index("filename")
        parts.append((data, [file_digest(Path(root) / ln.split(",")[col]) for ln in lines[1:] if ln]))
    return fingerprint(parts)


def save_digests(path: Path, digests: Sequence[bytes]) -> None:
    """Keep a finished trajectory's frame digests (resumption reads them instead of the frames)."""
    write_bytes(path, b"".join(digests))


def load_digests(path: Path, n: int) -> list[bytes] | None:
    """The ``n`` digests saved at ``path``; None when absent or of another length."""
    if not path.is_file():
        return None
    data = path.read_bytes()
    if len(data) != 32 * n:
        return None
    return [data[i:i + 32] for i in range(0, len(data), 32)]
