"""Decode every frame once into a memory-mapped uint8 array, and normalisation statistics from it.

``FrameCache.open_or_build(dataset, image_size, cache_dir)`` returns the cache
``<cache_dir>/frames-<fingerprint[:12]>-<key>-<H>x<W>.npy``: a NumPy ``.npy``
file holding ``uint8[n_frames, 3, H, W]`` (channel-first, RGB), row ``i`` =
global frame index ``i`` of ``dataset.frames``. The key hashes the dataset
fingerprint, the output size, the ordered frame file names and the cache
format version, so a changed dataset or size gets a new file and an unchanged
one is reused by every later epoch, run and process: PNGs are decoded once.

A frame rewritten in place (same name, new pixels) does not change a recorded
content fingerprint, so the sidecar ``.json`` also records every frame file's
size and ``mtime_ns`` as they were before it was decoded; opening the cache
stats every frame (about a second per 800k frames) and rebuilds it, with one
warning naming the first changed file, when any differs.

Building decodes with Pillow on a thread pool (Pillow releases the GIL while
decoding), converts to RGB and, when the size differs from the dataset's,
resizes with Pillow's antialiased bilinear filter. The array is written under
a unique temporary name and moved into place with ``os.replace``; an advisory
lock file (``fcntl.lockf``) makes a second process that asks for the same
cache wait and then reuse it instead of decoding again. Without the lock
(other OSes, or file systems without locking) two builders still only race to
``os.replace`` identical files, so the cache is never half-written.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import os
import zlib
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
from PIL import Image
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

from ..config import Config
from ..errors import DataError
from ..io import atomic_path, file_lock, write_json
from .reader import Dataset

CACHE_VERSION = 2  # 2: the sidecar records each frame file's size and mtime
_CHUNK = 256  # frames per thread task
log = logging.getLogger(__name__)


def decode_frame(path: str, shape: tuple[int, int] | None) -> np.ndarray:
    """Decode one image file to ``uint8[3, H, W]`` RGB, resized to ``shape`` (H, W) when given."""
    return _decode(path, shape)[0]


def _decode(path: str, shape: tuple[int, int] | None) -> tuple[np.ndarray, str, tuple[int, int]]:
    """The frame as ``decode_frame`` gives it, its mode on disk (``L``: grayscale, ...) and its (H, W) on disk."""
    try:
        with Image.open(path) as im:
            mode, native = im.mode, (im.size[1], im.size[0])
            im = im.convert("RGB")
            if shape is not None and im.size != (shape[1], shape[0]):
                im = im.resize((shape[1], shape[0]), Image.Resampling.BILINEAR)
            return np.asarray(im).transpose(2, 0, 1), mode, native
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:  # Pillow's parse errors
        raise DataError(f"{path}: cannot decode frame ({exc or type(exc).__name__}); re-render or replace the file"
                        ) from None


def resolve_image_size(image_size: int | None, dataset: Dataset) -> tuple[int, int]:
    """Output frame shape (H, W): ``data.image_size`` squared, or the dataset's own shape when None."""
    if image_size is not None:
        return int(image_size), int(image_size)
    return dataset.frame_shape


def input_size(image_size: int | None, dataset: Dataset) -> int:
    """The square network input side: ``data.image_size``, or the dataset's own when it is None."""
    if image_size is not None:
        return int(image_size)
    if dataset.image_size is None:
        h, w = dataset.frame_shape
        raise DataError(f"{dataset.root}: frames are {w}x{h} (not square); set data.image_size to resize them")
    return dataset.image_size


def open_frame_cache(cfg: Config, dataset: Dataset, progress: bool = True) -> FrameCache:
    """The frame cache for a run: ``data.image_size`` (default: the dataset's) under ``data.cache_dir``."""
    if not dataset.has_frames:
        raise DataError(f"{dataset.root}: a poses-only dataset (dataset.csv.columns.filename is null) has no frames "
                        "to train on; name the image column in dataset.csv.columns.filename")
    return FrameCache.open_or_build(dataset, input_size(cfg.data.image_size, dataset), cfg.paths.cache,
                                    progress=progress, threads=cfg.data.workers or None)


def cache_key(dataset: Dataset, shape: tuple[int, int]) -> str:
    h = hashlib.sha256(f"v{CACHE_VERSION}\0{dataset.fingerprint}\0{shape[0]}x{shape[1]}\0".encode())
    h.update("\n".join(dataset.frames["filename"]).encode())
    return h.hexdigest()[:16]


class FrameCache:
    """Decoded frames ``uint8[n, 3, H, W]``, memory-mapped read-only and opened lazily in each process.

    Pickling drops the open memory map, so a DataLoader worker reopens the
    file on first use instead of receiving a copy of the frames.
    """

    def __init__(self, path: str | os.PathLike, shape: tuple[int, int, int, int]):
        self.path = Path(path)
        self.shape = tuple(int(s) for s in shape)
        self._array: np.ndarray | None = None

    # -- access ------------------------------------------------------------
    @property
    def array(self) -> np.ndarray:
        if self._array is None:
            self._array = np.load(self.path, mmap_mode="r")
        return self._array

    @property
    def image_shape(self) -> tuple[int, int]:
        return self.shape[2], self.shape[3]

    def __len__(self) -> int:
        return self.shape[0]

    def take(self, indices: np.ndarray) -> np.ndarray:
        """Frames at global ``indices`` as a new writable ``uint8[len, 3, H, W]`` array."""
        indices = np.asarray(indices, dtype=np.int64)
        if len(indices) and indices[-1] - indices[0] == len(indices) - 1 and np.all(np.diff(indices) == 1):
            return np.array(self.array[indices[0]: indices[-1] + 1])  # one contiguous read
        return np.array(self.array[indices])

    def __getstate__(self) -> dict:
        return {"path": self.path, "shape": self.shape, "_array": None}

    def __repr__(self) -> str:
        return f"FrameCache({self.path.name}, {self.shape})"

    # -- building ------------------------------------------------------------
    @staticmethod
    def _valid(path: Path, shape: tuple[int, ...]) -> bool:
        try:
            arr = np.load(path, mmap_mode="r")
        except (OSError, ValueError):
            return False
        return arr.dtype == np.uint8 and tuple(arr.shape) == tuple(shape)

    @classmethod
    def _stale(cls, path: Path, shape: tuple[int, ...], paths: Sequence[str]) -> str | None:
        """None when the cache file is whole and every frame is as it was decoded; else why it must be built."""
        if not cls._valid(path, shape):
            return "missing"
        recorded = _recorded_stats(path.with_suffix(".json"), len(paths))
        if recorded is None:
            return "unverifiable"
        return first_changed(paths, recorded)

    @classmethod
    def open_or_build(cls, dataset: Dataset, image_size: int | None, cache_dir: str | os.PathLike,
                      progress: bool = True, threads: int | None = None) -> FrameCache:
        """The cache of ``dataset`` at ``image_size`` (None: the dataset's own size), built if missing or stale."""
        hw = resolve_image_size(image_size, dataset)
        shape = (dataset.n_frames, 3, *hw)
        cache_dir = Path(cache_dir)
        cache_dir.mkdir(parents=True, exist_ok=True)
        path = cache_dir / f"frames-{dataset.fingerprint[:12]}-{cache_key(dataset, hw)}-{hw[0]}x{hw[1]}.npy"
        paths = dataset.frames["path"].tolist()
        if cls._stale(path, shape, paths) is not None:
            with file_lock(path.with_suffix(".lock")):
                why = cls._stale(path, shape, paths)  # another process may have built it while we waited
                if why is not None:
                    if why not in ("missing", "unverifiable"):
                        log.warning("frame cache %s: %s changed since the cache was built; rebuilding it",
                                    path.name, why)
                    _build(dataset, hw if image_size is not None else None, shape, path, progress, threads)
        return cls(path, shape)


def frame_stats(paths: Sequence[str]) -> np.ndarray:
    """``int64[n, 2]``: size and mtime_ns of each frame file (-1, -1 for a missing one)."""
    out = np.full((len(paths), 2), -1, dtype=np.int64)
    for i, p in enumerate(paths):
        try:
            st = os.stat(p)
        except OSError:
            continue
        out[i] = st.st_size, st.st_mtime_ns
    return out


def first_changed(paths: Sequence[str], recorded: np.ndarray) -> str | None:
    """The first frame whose size or mtime differs from ``recorded`` (or that is gone), or None."""
    now = frame_stats(paths)
    bad = np.flatnonzero((now != recorded).any(1))
    return None if not len(bad) else str(paths[int(bad[0])])


def _pack(stats: np.ndarray) -> str:
    return base64.b64encode(zlib.compress(stats.astype("<i8").tobytes(), 1)).decode("ascii")


def _recorded_stats(sidecar: Path, n: int) -> np.ndarray | None:
    try:
        meta = json.loads(sidecar.read_text(encoding="utf-8"))
        raw = zlib.decompress(base64.b64decode(meta["frame_stats"]))
        return np.frombuffer(raw, dtype="<i8").reshape(n, 2)
    except (OSError, ValueError, KeyError, TypeError, zlib.error):  # absent, older format or damaged
        return None


@dataclass
class _Chunk:
    """What decoding a chunk of frames found besides pixels: frames converted to RGB or of another size."""

    done: int
    converted: list[tuple[str, str]] = field(default_factory=list)  # (path, mode on disk)
    resized: list[tuple[str, tuple[int, int]]] = field(default_factory=list)  # (path, (H, W) on disk)


def _decode_chunk(out: np.ndarray, paths: np.ndarray, resize: tuple[int, int] | None,
                  native: tuple[int, int], start: int) -> _Chunk:
    """Decode frames ``start .. start+_CHUNK`` into ``out``; ``native``: the dataset's (H, W) on disk."""
    expected = out.shape[1:]
    stop = min(start + _CHUNK, len(paths))
    chunk = _Chunk(stop - start)
    for i in range(start, stop):
        frame, mode, size = _decode(paths[i], resize)
        if frame.shape != expected:
            raise DataError(f"{paths[i]}: frame is {frame.shape[2]}x{frame.shape[1]} pixels, the dataset's "
                            f"are {expected[2]}x{expected[1]}; set data.image_size to resize every frame")
        if mode != "RGB":
            chunk.converted.append((str(paths[i]), mode))
        if size != tuple(native):
            chunk.resized.append((str(paths[i]), size))
        out[i] = frame
    return chunk


def _warn_degraded(chunks: Sequence[_Chunk], native: tuple[int, int]) -> None:
    """One warning per kind of silent change to frames: converted to RGB, or of another size and resized."""
    converted = [c for ch in chunks for c in ch.converted]
    resized = [r for ch in chunks for r in ch.resized]
    if converted:
        modes = sorted({m for _, m in converted})
        log.warning("warning: %d frame(s) were not RGB (mode %s, e.g. %s) and were converted to RGB",
                    len(converted), "/".join(modes), converted[0][0])
    if resized:
        (h, w) = resized[0][1]
        log.warning("warning: %d frame(s) were not the dataset's %dx%d pixels (e.g. %s is %dx%d) and were resized "
                    "to data.image_size", len(resized), native[1], native[0], resized[0][0], w, h)


def _build(dataset: Dataset, resize: tuple[int, int] | None, shape: tuple[int, ...], path: Path,
           progress: bool, threads: int | None) -> None:
    paths = dataset.frames["path"].to_numpy()
    stats = frame_stats(paths)  # before decoding: a frame rewritten during the build is caught next time
    with atomic_path(path) as tmp:
        out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=shape)
        pool = ThreadPoolExecutor(threads or min(8, os.cpu_count() or 1))
        try:
            chunks = []
            with _progress(progress, len(paths), path.name) as advance:
                for chunk in pool.map(partial(_decode_chunk, out, paths, resize, tuple(dataset.frame_shape)),
                                      range(0, len(paths), _CHUNK)):
                    advance(chunk.done)
                    chunks.append(chunk)
        finally:  # on an error or Ctrl-C, drop the chunks not started yet
            pool.shutdown(wait=True, cancel_futures=True)
        out.flush()
        del out  # closes the memory map before the rename
    _warn_degraded(chunks, tuple(dataset.frame_shape))
    write_json(path.with_suffix(".json"), {
        "dataset": str(dataset.root), "fingerprint": dataset.fingerprint, "shape": list(shape),
        "layout": "uint8[n_frames, 3, H, W] RGB", "version": CACHE_VERSION,
        "frame_stats_layout": "zlib + base64 of little-endian int64[n_frames, 2]: file size, mtime_ns",
        "frame_stats": _pack(stats)})


@contextmanager
def _progress(enabled: bool, total: int, name: str):
    if not enabled:
        yield lambda n: None
        return
    with Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), transient=True) as bar:
        task = bar.add_task(f"decoding frames into {name}", total=total)
        yield lambda n: bar.advance(task, n)


def channel_stats(cache: FrameCache, frame_indices: Sequence[int] | np.ndarray,
                  max_frames: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and std (population, in [0, 1] units) over the given frames.

    Call it with the training split's frame indices only. Above ``max_frames``
    frames an evenly spaced subset of that many is used (deterministic).
    """
    idx = np.unique(np.asarray(frame_indices, dtype=np.int64))
    if len(idx) == 0:
        raise DataError("channel_stats: no frames given (is the training split empty?)")
    if len(idx) > max_frames:
        idx = idx[np.linspace(0, len(idx) - 1, max_frames).round().astype(np.int64)]
    total = np.zeros(3)
    squares = np.zeros(3)
    for start in range(0, len(idx), 256):
        x = cache.take(idx[start: start + 256]).astype(np.float64) / 255.0
        total += x.sum((0, 2, 3))
        squares += (x * x).sum((0, 2, 3))
    n = len(idx) * cache.shape[2] * cache.shape[3]
    mean = total / n
    std = np.sqrt(np.maximum(squares / n - mean * mean, 0.0))
    return mean, std
