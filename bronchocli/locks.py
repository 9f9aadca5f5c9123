"""An inter-process file lock for work that two processes on one machine must not do at once.

Used where concurrent first-time set-up would race: building the frame cache,
generating a dataset, creating the MLflow or Optuna tables of a SQLite store.
POSIX advisory locks (``fcntl.flock``); where the platform or file system has
none, the lock is a no-op and callers rely on their atomic renames.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


@contextmanager
def file_lock(path: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` (created if missing, never deleted) for the ``with`` block."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    with open(path, "a+b") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX)
        except OSError:  # a file system without locks
            yield
            return
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
