"""What ``track`` reads: a folder of frames, a video file, or one trajectory of a dataset (with its poses).

``open_input(path)`` returns a :class:`FrameInput` whose ``frames()`` yields
uint8 ``[H, W, 3]`` RGB frames in time order, one at a time (a long video
is never held in memory whole):

* a **folder**: its image files (``.png .jpg .jpeg .bmp .tif .tiff``) in
  natural name order (``f2`` before ``f10``); every frame must have the same
  size;
* a **video file** (any container/codec FFmpeg reads: ``.mp4 .mkv .avi
  .mov ...``), decoded with PyAV (``pip install 'bronchocli[video]'``);
* **one trajectory of a dataset**: ``<dataset root>/<patient>/<lobe>/<trajectory>``
  (the trajectory's key after the root, e.g. ``data/tiny/p00/ur/2``); its
  ground-truth poses and voxel spacing come along.

Bad input is a ``DataError`` (one line, exit 2): nothing there, no frames,
fewer than two, mixed sizes, an unreadable image or video.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image

from .. import extras
from ..data.naming import DATASET_JSON
from ..data.reader import DISK_POSE_COLUMNS, POSE_COLUMNS, open_dataset_dir
from ..errors import DataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class GroundTruth:
    poses: np.ndarray  # (N, 6) absolute poses: voxels, intrinsic XYZ Euler degrees
    spacing_mm: np.ndarray  # (3,) voxel size; NaN when unknown
    key: str = ""  # patient/lobe/trajectory when it comes from a dataset
    source: str = ""


@dataclass(frozen=True)
class FrameInput:
    name: str  # what the user gave, for messages and output names
    kind: str  # folder, video or trajectory
    shape: tuple[int, int]  # (H, W) of every frame
    n_frames: int | None  # None when a video does not say
    frames: Callable[[], Iterator[np.ndarray]]  # a fresh iterator of uint8 [H, W, 3] frames each call
    labels: tuple[str, ...] = ()  # per frame: its file name (folders, trajectories)
    ground_truth: GroundTruth | None = None


def natural_order(name: str) -> tuple:
    """Sort key putting ``f2`` before ``f10``: runs of digits compare as numbers."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name) if part)


def decode_image(path: str | Path) -> np.ndarray:
    """One image file -> uint8 ``[H, W, 3]`` RGB."""
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except OSError as exc:
        raise DataError(f"{path}: cannot decode frame ({exc})") from None


def _image_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:  # reads the header only
            return im.size[1], im.size[0]
    except OSError as exc:
        raise DataError(f"{path}: cannot decode frame ({exc})") from None


def _same_size(paths: list[Path], what: str) -> tuple[int, int]:
    if len(paths) < 2:
        raise DataError(f"{what}: {len(paths)} frame(s); tracking needs at least 2")
    first = _image_size(paths[0])
    for p in paths[1:]:
        size = _image_size(p)
        if size != first:
            raise DataError(f"{p}: frame is {size[1]}x{size[0]} pixels, {paths[0].name} is {first[1]}x{first[0]}; "
                            "every frame of one input must have the same size")
    return first


def _images(paths: list[Path]) -> Callable[[], Iterator[np.ndarray]]:
    return lambda: (decode_image(p) for p in paths)


def open_folder(path: Path) -> FrameInput:
    paths = sorted((p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                   key=lambda p: natural_order(p.name))
    if not paths:
        raise DataError(f"{path}: no frames (image files {' '.join(IMAGE_SUFFIXES)}) in this folder")
    shape = _same_size(paths, str(path))
    return FrameInput(str(path), "folder", shape, len(paths), _images(paths), tuple(p.name for p in paths))


def _av():
    extras.require("video", "reading a video")  # one line naming the [video] extra, as for every optional module
    import av  # lazy: PyAV (FFmpeg) only for videos, an optional extra

    return av


def _video_frames(path: Path) -> Iterator[np.ndarray]:
    av = _av()
    try:
        with av.open(str(path)) as container:
            for frame in container.decode(video=0):
                yield frame.to_ndarray(format="rgb24")
    except (av.FFmpegError, ValueError, IndexError) as exc:
        raise DataError(f"{path}: cannot decode the video ({exc})") from None


def open_video(path: Path) -> FrameInput:
    av = _av()
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise DataError(f"{path}: no video stream in this file")
            stream = container.streams.video[0]
            first = next(container.decode(stream), None)
            n = int(stream.frames or 0) or None
    except av.FFmpegError as exc:
        raise DataError(f"{path}: not a readable video ({exc})") from None
    if first is None:
        raise DataError(f"{path}: the video has no frames")
    if n is not None and n < 2:
        raise DataError(f"{path}: the video has {n} frame; tracking needs at least 2")
    return FrameInput(str(path), "video", (first.height, first.width), n, lambda: _video_frames(path))


def dataset_root_of(path: Path) -> Path | None:
    """The dataset root when ``path`` is ``<root>/<patient>/<lobe>/<trajectory>`` of a dataset, else None."""
    parts = path.parts
    if len(parts) < 3:
        return None
    root = Path(*parts[:-3]) if len(parts) > 3 else Path(".")
    return root if (root / DATASET_JSON).is_file() else None


def open_trajectory(root: Path, key: str, name: str) -> FrameInput:
    dataset = open_dataset_dir(root)
    traj = dataset.trajectory(key)
    if not dataset.has_frames:
        raise DataError(f"{root}: a poses-only dataset has no frames to track")
    paths = [Path(f) for f in traj.filenames]
    shape = _same_size(paths, name)
    truth = GroundTruth(np.asarray(traj.poses, dtype=np.float64), dataset.spacing_mm(traj.patient), traj.key, name)
    return FrameInput(name, "trajectory", shape, len(paths), _images(paths), tuple(p.name for p in paths), truth)


def open_input(path: str | Path) -> FrameInput:
    """A folder of frames, a video file, or ``<dataset>/<patient>/<lobe>/<trajectory>`` (see the module doc)."""
    p = Path(path).expanduser()
    if p.is_dir():
        return open_folder(p)
    if p.is_file():
        return open_video(p)
    root = dataset_root_of(p)
    if root is not None:
        return open_trajectory(root, "/".join(p.parts[-3:]), str(path))
    raise DataError(f"{path}: not found (give a folder of frames, a video file, or "
                    "<dataset root>/<patient>/<lobe>/<trajectory>)")


def read_ground_truth(path: str | Path) -> GroundTruth:
    """Poses to score against: a dataset trajectory (as for :func:`open_input`) or a CSV, one row per frame.

    The CSV needs the pose columns of a dataset CSV (``pos_x pos_y pos_z Rx Ry Rz``) or of ``track``'s output
    (the same names); a ``frame`` column, when present, orders the rows. Voxel spacing is unknown for a CSV
    (millimetre errors are NaN)."""
    p = Path(path).expanduser()
    root = None if p.is_file() else dataset_root_of(p)
    if root is not None:
        truth = open_trajectory(root, "/".join(p.parts[-3:]), str(path)).ground_truth
        assert truth is not None
        return truth
    if not p.is_file():
        raise DataError(f"--ground-truth {path}: not found (a pose CSV, or <dataset root>/<patient>/<lobe>/<trajectory>)")
    try:
        table = pd.read_csv(p)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise DataError(f"{p}: not a readable CSV ({str(exc).splitlines()[0]})") from None
    for names in (DISK_POSE_COLUMNS, POSE_COLUMNS):
        if all(c in table.columns for c in names):
            if "frame" in table.columns:
                table = table.sort_values("frame", kind="stable")
            poses = table[list(names)].apply(pd.to_numeric, errors="coerce").to_numpy(np.float64)
            if not np.isfinite(poses).all():
                row = int(np.flatnonzero(~np.isfinite(poses).all(1))[0])
                raise DataError(f"{p} line {row + 2}: non-finite pose value")
            return GroundTruth(poses, np.full(3, np.nan), "", str(p))
    raise DataError(f"{p}: needs the pose columns {' '.join(DISK_POSE_COLUMNS)} (found: {' '.join(map(str, table.columns))})")
