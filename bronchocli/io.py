"""Files: atomic writes, an inter-process lock, figures, VTK ``.vtp`` surfaces.

Every finished file of the project is written through :func:`atomic_path`: to
a unique temporary name in the target's own directory, then moved into place
with ``os.replace``, so a reader (or a crash) never sees half a file.
:func:`file_lock` (the ``filelock`` package) serialises first-time set-up between processes of one
machine (building a frame cache, generating a dataset, creating a SQLite
store's tables). :func:`folder_bytes` and :func:`fmt_bytes` size and print
what lies on disk (``status``, ``sweep gc``, a checkpoint's space check).
"""

from __future__ import annotations

import json
import os
import re
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from filelock import FileLock

from .errors import DataError

TEMP_SUFFIX = ".tmp"


def temp_name(path: Path) -> Path:
    """A hidden name beside ``path``, unique per process and call."""
    return path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}{TEMP_SUFFIX}")


@contextmanager
def atomic_path(path: str | os.PathLike, private: bool = False) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path``, on error it is removed.

    ``private``: the temporary file exists already, readable and writable by this user only (0600) from its
    first byte (a secret is never readable by others, not even while it is written)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    try:
        if private:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
            os.chmod(tmp, 0o600)  # O_CREAT's mode is masked by the umask; 0600 is never wider than asked
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: str | os.PathLike, data: bytes, private: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically (``private``: mode 0600 from the first byte, and flushed to disk)."""
    with atomic_path(path, private) as tmp:
        with open(tmp, "r+b" if private else "wb") as f:
            f.write(data)
            if private:
                f.truncate()
                f.flush()
                os.fsync(f.fileno())
    return Path(path)


def write_text(path: str | os.PathLike, text: str, private: bool = False) -> Path:
    return write_bytes(path, text.encode("utf-8"), private)


def write_json(path: str | os.PathLike, data: Any) -> Path:
    return write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


_TEMP_NAME = re.compile(rf"^\..+\.\d+-[0-9a-f]{{8}}{re.escape(TEMP_SUFFIX)}$")  # what temp_name makes


def is_temp_name(name: str) -> bool:
    """A name :func:`temp_name` makes (a user's ``.notes.tmp`` is not one)."""
    return bool(_TEMP_NAME.match(name))


def remove_stale_temps(folder: Path) -> int:
    """Delete the temporary files interrupted writers left under ``folder`` (only names :func:`temp_name`
    makes, never a link); returns how many."""
    n = 0
    for p in Path(folder).rglob(f".*{TEMP_SUFFIX}"):
        if is_temp_name(p.name) and p.is_file() and not p.is_symlink():
            p.unlink(missing_ok=True)
            n += 1
    return n


def folder_bytes(folder: str | os.PathLike, only: Callable[[str], bool] | None = None) -> int:
    """Bytes of the files under ``folder`` (links not followed; 0 when it does not exist); ``only``: count the
    files whose name it accepts."""
    total = 0
    for dirpath, _, files in os.walk(folder):
        for name in files:
            if only is not None and not only(name):
                continue
            try:
                total += os.lstat(os.path.join(dirpath, name)).st_size
            except OSError:  # removed while we walked
                pass
    return total


def fmt_bytes(n: float | None) -> str:
    """``1.5 KB``, ``2.5 MB``: decimal units (1 KB = 1000 B, as disk sizes are sold and ``df -H`` prints them);
    None (nothing there) is ``none``."""
    if n is None:
        return "none"
    for unit in ("B", "KB", "MB", "GB"):
        if abs(n) < 1000:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"


@contextmanager
def file_lock(path: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive advisory lock on ``path`` (created, never deleted) for the ``with`` block.

    The ``filelock`` package's ``FileLock`` (``flock`` on POSIX, ``msvcrt`` on Windows); a file system without
    locks raises instead of silently not locking.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(str(path)):
        yield


def save_figure(fig, path: str | os.PathLike, formats: Sequence[str] = ("png",), dpi: int = 130) -> list[Path]:
    """Save a matplotlib figure as ``path`` with each suffix in ``formats``, atomically, and close it."""
    import matplotlib.pyplot as plt  # lazy: matplotlib (~0.5 s) only where a figure is drawn

    path = Path(path)
    written = []
    for fmt in formats:
        target = path.with_suffix(f".{fmt}")
        with atomic_path(target) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format=fmt)
        written.append(target)
    plt.close(fig)
    return written


def read_polydata(path: str | os.PathLike):
    """A ``.vtp`` surface as ``vtkPolyData``; DataError when it is missing or empty."""
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader  # lazy: VTK is optional outside generation

    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    out = reader.GetOutput()
    if out is None or out.GetNumberOfPoints() == 0:
        raise DataError(f"{path}: not a readable surface (.vtp)")
    return out


def write_polydata(poly, path: str | os.PathLike, what: str = "surface") -> Path:
    """Write ``poly`` as binary VTK XML (``.vtp``) atomically; DataError when VTK cannot serialise it.

    VTK builds the file in memory and Python writes it: VTK's own file writer corrupts its heap when the disk
    fills mid-write (a segfault, or "double free or corruption" later), where Python's write raises an OSError
    (ENOSPC) that the caller words as one line."""
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter  # lazy: VTK is optional outside generation

    path = Path(path)
    writer = vtkXMLPolyDataWriter()
    writer.SetInputData(poly)
    writer.SetDataModeToBinary()  # base64 inline: the output string is ASCII
    writer.SetWriteToOutputString(1)
    if not writer.Write():
        raise DataError(f"{path}: could not write the {what}")
    text = writer.GetOutputString()
    return write_bytes(path, text.encode("utf-8") if isinstance(text, str) else bytes(text))
