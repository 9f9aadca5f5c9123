"""Resumable training checkpoints: plain data only, loaded without running code, written only when they fit.

A checkpoint (``runs.contract.resume_file``: ``<runs.checkpoints>/<run_id>/last.pt``)
holds tensors, dicts, lists, tuples, strings, numbers, booleans and None: nothing
else. It is read with ``torch.load(weights_only=True)``, whose unpickler refuses
every other object, so a file planted on shared storage cannot run code in the
process that resumes from it. The RNG states that are not tensors (numpy's
``MT19937`` tuple, Python's ``random`` state) are converted to tensors and ints.
CUDA's RNG state is that of the *current* device only, restored onto the current
device, so a run checkpointed on an 8-GPU node resumes on a worker that sees one
GPU (a Slurm requeue), or on the CPU.

``load`` checks the format version, the keys, and that the file belongs to the
run and cell that resume it; anything else is :class:`BadCheckpoint` (one line
naming the file). ``save`` checks the free space first (a checkpoint needs
about twice its size: the temporary copy is written beside the old file) and
writes atomically; a failed write removes the temporary file and raises
:class:`CheckpointWriteError` naming the path and the space needed.
"""

from __future__ import annotations

import errno
import os
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .. import io, pathcheck, urls
from ..config import Config
from ..errors import BronchoError, CheckpointWriteError, WriteFailed  # resumable kinds: defined with the others
from ..retry import disk_full, disk_full_line
from ..runs.ownership import CHECKPOINT_FORMAT, mark

FORMAT = CHECKPOINT_FORMAT  # runs.ownership reads it back (without torch) to prove a folder is a checkpoint's
KEYS = ("format", "run_id", "cell_key", "model", "optimizer", "scheduler", "scaler", "step", "micro", "best_val",
        "best_step", "best_state", "bad", "history", "times", "rng")
SPACE_FACTOR = 2  # free space a checkpoint needs, in multiples of its size (temporary copy beside the old file)
OVERHEAD = 1 << 16  # bytes added to the tensors' size for the zip container and the non-tensor entries


class BadCheckpoint(BronchoError):
    """A checkpoint file that is not a valid checkpoint of this run (refused, never executed)."""


def as_write_failure(exc: BaseException, need: int | None = None, where: Path | None = None) -> WriteFailed | None:
    """A WriteFailed (one line naming the folder, the space free there and, given ``need`` in bytes, the space the
    run needs) for an error of the disk under the run (its own or one it was raised from); None for any other.
    ``where``: the folder to name when the error names no file (SQLite's "database or disk is full")."""
    if isinstance(exc, WriteFailed):
        if need and "needs about" not in str(exc) and NOT_WRITABLE_MARK not in str(exc):
            return type(exc)(f"{exc}; the run needs about {io.fmt_bytes(need)} free to finish")
        return exc
    full = disk_full(exc)
    if full is None:
        return None
    why, file = full
    if isinstance(exc, OSError) and exc.errno == errno.EROFS:  # read-only, not full: no space to free
        return WriteFailed(f"{file or where}: {NOT_WRITABLE_MARK} (read-only file system), not full; make it "
                           "writable again and run the same command again: it resumes the run from its checkpoint")
    line = disk_full_line(file or where, why, need) if (file or where) else urls.error_line(exc, 200)
    return WriteFailed(f"{line}; free space there and run the same command again: it resumes the run from its "
                       "checkpoint")


# -- a reserve on the stores' disk ------------------------------------------------------------------------------
# A full disk must not leave the run RUNNING: the writes that end it (its status, its failure reason, the sweep's
# claims row) need a few pages of the SQLite stores. A small file beside them holds that room while the run
# trains; a run that meets a full disk deletes it before ending the run, and the next run puts it back.

RESERVE_NAME = ".bronchopose-reserve"
RESERVE_BYTES = 4 << 20
# put wherever it takes at most half of what is free: on any disk with room for it, however little (a nearly
# full disk needs it most: its runs are the ones that meet a full disk), never the reserve that fills a disk
RESERVE_ROOM = 2 * RESERVE_BYTES


def reserve(folders: list[Path]) -> None:
    """Put a RESERVE_BYTES file in each existing folder (one per file system) that lacks one and has room."""
    for folder in _one_per_disk(folders):
        path = folder / RESERVE_NAME
        try:
            if path.is_file() or shutil.disk_usage(folder).free < RESERVE_ROOM:
                continue
            with io.atomic_path(path) as tmp:
                with open(tmp, "wb") as f:
                    f.write(b"\0" * RESERVE_BYTES)  # written, not sparse: the blocks are really held
        except OSError:
            continue  # a reserve is a courtesy: never the run's failure


def release_reserve(folders: list[Path]) -> bool:
    """Delete the reserves of ``folders`` (a full disk met): True when one was there."""
    freed = False
    for folder in folders:
        try:
            (folder / RESERVE_NAME).unlink()
            freed = True
        except OSError:
            pass
    return freed


def store_folders(cfg: Config) -> list[Path]:
    """The folders of the config's SQLite stores (MLflow's, the sweep's claims): where a reserve is kept."""
    dbs = [urls.sqlite_file(u) for u in (cfg.paths.mlflow_uri, cfg.paths.storage_url)]
    return list(dict.fromkeys(db.parent for db in dbs if db is not None))


def failure_folder(cfg: Config) -> Path:
    """The folder a full disk is named by when the error names no file (SQLite's "database or disk is full"):
    the MLflow SQLite store's, else the checkpoints'."""
    db = urls.sqlite_file(cfg.paths.mlflow_uri)
    return db.parent if db is not None else cfg.paths.checkpoints


def run_needs(ckpt_dir: Path) -> int | None:
    """Bytes a run that met a full disk needs to finish: about its checkpoint's size (the model it still has to
    log, its predictions and its next checkpoint are smaller); None before its first checkpoint."""
    try:
        return (Path(ckpt_dir) / "last.pt").stat().st_size
    except OSError:
        return None


def _one_per_disk(folders: list[Path]) -> list[Path]:
    seen, out = set(), []
    for folder in folders:
        try:
            dev = folder.stat().st_dev
        except OSError:
            continue
        if dev not in seen:
            seen.add(dev)
            out.append(folder)
    return out


# -- RNG states as plain data -------------------------------------------------------------------------------


def rng_state() -> dict[str, Any]:
    """Every RNG the loop draws from, as tensors and plain numbers (CUDA: the current device only)."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {"kind": str(kind), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64).copy()),
                  "pos": int(pos), "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
        "python": (int(version), tuple(int(v) for v in internal), None if gauss_next is None else float(gauss_next)),
        "cuda": torch.cuda.get_rng_state() if torch.cuda.is_available() else None,
    }


def set_rng_state(rng: dict[str, Any]) -> None:
    """Restore :func:`rng_state`'s output; the CUDA state goes to the current device (if there is one)."""
    torch.set_rng_state(rng["torch"])
    n = rng["numpy"]
    keys = n["keys"].numpy().astype(np.uint32)
    np.random.set_state((n["kind"], keys, int(n["pos"]), int(n["has_gauss"]), float(n["cached_gaussian"])))
    version, internal, gauss_next = rng["python"]
    random.setstate((int(version), tuple(int(v) for v in internal), gauss_next))
    if rng.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state(rng["cuda"])


# -- size and space -----------------------------------------------------------------------------------------


def nbytes(obj: Any) -> int:
    """Bytes the tensors of ``obj`` occupy (shared storages counted once), plus the container's overhead."""
    seen: dict[int, int] = {}

    def walk(x: Any) -> None:
        if isinstance(x, torch.Tensor):
            st = x.untyped_storage()
            seen[st.data_ptr() or id(st)] = st.nbytes()
        elif isinstance(x, dict):
            for v in x.values():
                walk(v)
        elif isinstance(x, (list, tuple)):
            for v in x:
                walk(v)

    walk(obj)
    return sum(seen.values()) + OVERHEAD


def check_space(path: Path, need: int, what: str = "checkpoint") -> None:
    """CheckpointWriteError (one line) unless the file system of ``path`` has ``need`` bytes free."""
    try:
        folder = pathcheck.nearest_existing(path.parent)
        free = shutil.disk_usage(folder).free
        read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):  # cannot tell (e.g. a file system without statvfs): let the write decide
        return
    if read_only:  # its free space is beside the point
        raise CheckpointWriteError(not_writable_line(path, errno.EROFS))
    if free < need:
        raise CheckpointWriteError(
            f"{path}: not enough disk space for the {what}: needs {io.fmt_bytes(need)} free ({SPACE_FACTOR}x its "
            f"size), {io.fmt_bytes(free)} available on the file system mounted at {pathcheck.mount_point(folder)}; "
            "free space there or point runs.checkpoints elsewhere")


def check_space_for(path: Path, state: dict[str, Any]) -> int:
    """Check there is room for ``state`` at ``path``; returns the bytes needed."""
    need = SPACE_FACTOR * nbytes(state)
    check_space(path, need)
    return need


# -- save / load ----------------------------------------------------------------------------------------------


def _is_write_failure(exc: BaseException) -> bool:
    if isinstance(exc, OSError):
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and ("inline_container" in text or "PytorchStreamWriter" in text
                                              or "file write failed" in text or "unexpected pos" in text)


def save(path: str | os.PathLike, state: dict[str, Any]) -> Path:
    """Write ``state`` (plain data, see the module doc) atomically after checking the free space."""
    path = Path(path)
    state = {"format": FORMAT, **state}
    need = check_space_for(path, state)
    try:
        with io.atomic_path(path) as tmp:
            torch.save(state, tmp)
        if state.get("run_id") == path.parent.name:  # proves the folder is this run's (runs.ownership: gc, cleanup)
            mark(path.parent, state["run_id"], state.get("cell_key"))
    except (OSError, RuntimeError) as exc:
        if not _is_write_failure(exc):
            raise
        code = getattr(exc, "errno", None)
        if code in NOT_WRITABLE:  # a folder made read-only is not a full one: freeing space would not help
            raise CheckpointWriteError(not_writable_line(path, code)) from None
        why = os.strerror(code) if code in (errno.ENOSPC, errno.EIO, errno.EDQUOT) else urls.error_line(exc, 200)
        raise CheckpointWriteError(f"{path}: could not write the checkpoint ({why}{_free_on(path)}); it needs about "
                                   f"{io.fmt_bytes(need)} free there; free space or point runs.checkpoints "
                                   "elsewhere") from None
    return path


def _free_on(path: Path) -> str:
    """``; 1.2 MB free on the file system mounted at /mnt``: the disk a failed write met (empty if unknown)."""
    try:
        return (f"; {io.fmt_bytes(shutil.disk_usage(pathcheck.nearest_existing(path.parent)).free)} free on the "
                f"file system mounted at {pathcheck.mount_point(path.parent)}")
    except OSError:
        return ""


NOT_WRITABLE = (errno.EROFS, errno.EACCES, errno.EPERM)  # the folder refuses writes, whatever space it has
NOT_WRITABLE_MARK = "not writable"  # in the line of a not-writable folder: never read as a want of space


def not_writable_line(path: Path, code: int) -> str:
    """One line for a checkpoint refused by a read-only or forbidden folder (not a full disk)."""
    why = "read-only file system" if code == errno.EROFS else os.strerror(code).lower()
    return (f"{path}: could not write the checkpoint: {path.parent} is {NOT_WRITABLE_MARK} ({why}), not full; make "
            "it writable again (or point runs.checkpoints elsewhere) and run the same command again: it resumes "
            "the run from its last checkpoint")


def read_plain(path: Path, what: str, fix: str) -> Any:
    """``torch.load`` with ``weights_only=True``: a file holding anything but tensors and plain data is refused
    unloaded (its pickle never runs), as is a truncated or unreadable one: BadCheckpoint, one line."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - unpickling refused, truncated, not a zip, I/O error: all mean "bad"
        why = "it holds objects other than tensors and plain data (refused unloaded)" \
            if "weights_only" in str(exc) or "Unsupported global" in str(exc) else urls.error_line(exc, 200)
        raise BadCheckpoint(f"{what} {path}: not a valid {what}: {why}; {fix}") from None


def load(path: str | os.PathLike, *, run_id: str | None = None, cell_key: str | None = None) -> dict[str, Any]:
    """The checkpoint at ``path``, refused (BadCheckpoint, one line) unless it is a valid one of this run and cell."""
    path = Path(path)
    state = read_plain(path, "checkpoint", "delete it to start the cell afresh")
    if not isinstance(state, dict):
        raise BadCheckpoint(f"checkpoint {path}: not a valid checkpoint (a {type(state).__name__}, not a dict)")
    if state.get("format") != FORMAT:
        raise BadCheckpoint(f"checkpoint {path}: format {state.get('format')!r}, this version reads format "
                            f"{FORMAT}; delete it to start the cell afresh")
    missing = [k for k in KEYS if k not in state]
    if missing:
        raise BadCheckpoint(f"checkpoint {path}: not a valid checkpoint (missing {', '.join(missing)})")
    for key, want in (("run_id", run_id), ("cell_key", cell_key)):
        if want is not None and state[key] != want:
            raise BadCheckpoint(f"checkpoint {path}: belongs to {key} {state[key]!r}, not {want!r}; refused")
    return state
