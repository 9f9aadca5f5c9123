"""One ``train`` of a cell at a time: two ``bronchopose train`` of the same cell started together train it once.

``cell_turn`` holds an exclusive lock on ``<runs.checkpoints>/.train-cells/<experiment and cell>.lock`` from
before ``train`` looks for the cell's FINISHED run until its run has ended. A second ``train`` of the cell
says who holds it (host, process, since when) and waits for it to end (Ctrl-C stops waiting); it then finds the
first one's FINISHED run and reports it instead of training again (``--again`` trains another run, after the
first). The lock is the operating system's (``flock``): a process that dies holds nothing, so there is nothing
to go stale; the lock file is deleted by its holder when the turn ends (a waiter that locked a deleted file
notices it and takes the new one). It serialises the processes of one machine, or of machines that share
``runs.checkpoints`` on a file system with working locks (NFSv4, Lustre); a sweep's cells are claimed through
the sweep's claims table instead (docs/training.md).
"""

from __future__ import annotations

import hashlib
import os
import socket
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from ..cells import Cell
from ..config import Config

try:
    import fcntl
except ImportError:  # Windows: no flock; each `train` runs on its own (the check for a FINISHED run still holds)
    fcntl = None  # type: ignore[assignment]

FOLDER = ".train-cells"


def lock_path(cfg: Config, cell: Cell) -> Path:
    """The lock file of ``cell`` in ``cfg``'s experiment."""
    name = hashlib.sha256(f"{cfg.experiment_name}\0{cell.key}".encode()).hexdigest()[:24]
    return cfg.paths.checkpoints / FOLDER / f"{name}.lock"


def _holder(path: Path) -> str:
    try:
        text = path.read_text().strip()
    except OSError:
        text = ""
    return text or "another process"


@contextmanager
def cell_turn(cfg: Config, cell: Cell, say: Callable[[str], None]) -> Iterator[None]:
    """This process's turn at ``cell``: waits (saying so once) while another ``train`` of the cell holds it."""
    if fcntl is None:
        yield
        return
    path = lock_path(cfg, cell)
    fd = _lock(path, cell, say)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{socket.gethostname()} pid {os.getpid()} since {time.strftime('%H:%M:%S')}\n".encode(), 0)
        yield
    finally:
        try:
            path.unlink(missing_ok=True)  # while still locked: a waiter that then locks the old file sees it gone
            path.parent.rmdir()  # nothing else waits there
        except OSError:
            pass
        os.close(fd)  # releases the lock


def _lock(path: Path, cell: Cell, say: Callable[[str], None]) -> int:
    """An open, exclusively locked descriptor of ``path`` (the file that is there now)."""
    told = False
    while True:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except FileNotFoundError:  # the folder was removed between the two calls by a holder leaving: again
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if not told:
                    say(f"cell {cell.label} (key {cell.key}) is being trained by another `train` "
                        f"({_holder(path)}): waiting for it to end (Ctrl-C stops waiting)")
                    told = True
                fcntl.flock(fd, fcntl.LOCK_EX)
            if _same_file(fd, path):
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)  # the holder deleted the file we locked as it left: lock the one there now


def _same_file(fd: int, path: Path) -> bool:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    mine = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino)
