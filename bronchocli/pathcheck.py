"""A user's path, checked where it is resolved: the one home of what can go wrong with one, as one line each.

* ``expand``: ``${VAR}`` and ``~``; an undefined ``${VAR}`` is an error naming the setting and the variable
  (it would otherwise stay literal and become a folder named ``${VAR}``).
* ``resolve``: symlinks followed; a symlink loop (Python 3.11 raises RuntimeError "Symlink loop" from
  ``Path.resolve``, ``open``/``stat`` raise OSError ELOOP) is one line naming the setting. ``is_loop`` tells
  either exception apart, so the command line's last-resort handler words a loop met elsewhere the same way.
* ``check_writable_root``: an output root (artifacts, checkpoints, caches, logs) is never a system folder.
* ``check_output``: the one check of a path a command is about to write (a config's output root, a database
  file, ``--out`` of every command): not a system folder, the right kind if it exists, and creatable (its
  nearest existing folder writable, on a writable file system); creates nothing.
* ``outside``: names (a patient, a frame's ``filename``) that leave the folder they are relative to.
"""

from __future__ import annotations

import errno
import os
import re
from collections.abc import Sequence
from pathlib import Path

from .errors import BronchoError

_VAR = re.compile(r"\$\{([^}]*)\}")
# never an output root: the folder itself (the root of the file system, a home, a system tree) ...
SYSTEM_FOLDERS = ("/", "/bin", "/boot", "/dev", "/etc", "/home", "/lib", "/lib32", "/lib64", "/media", "/mnt",
                  "/opt", "/proc", "/root", "/run", "/sbin", "/srv", "/sys", "/tmp", "/usr", "/var", "/var/tmp")
# ... nor anything inside these (the operating system's own files)
SYSTEM_TREES = ("/bin", "/boot", "/dev", "/etc", "/lib", "/lib32", "/lib64", "/proc", "/sbin", "/sys", "/usr")
# ... except these folders inside them, made for users' files (/dev/shm: the shared-memory tmpfs every user may
# write, a fast place for runs/ or a cache, often reached through a symbolic link)
USER_TREES = ("/dev/shm",)


def expand(text: str, setting: str) -> str:
    """``text`` with its ``${VAR}``s expanded; an undefined one is a BronchoError naming ``setting`` and it."""
    for name in _VAR.findall(text):
        if name not in os.environ:
            raise BronchoError(f"{setting}: environment variable ${{{name}}} is not set; set it (export "
                               f"{name or 'NAME'}=...) or write the value itself")
    return os.path.expandvars(text)


def is_loop(exc: BaseException) -> bool:
    """Whether ``exc`` is a symlink loop: RuntimeError "Symlink loop" (Path.resolve) or OSError ELOOP."""
    if isinstance(exc, OSError):
        return exc.errno == errno.ELOOP
    return isinstance(exc, RuntimeError) and "symlink loop" in str(exc).lower()


def loop_error(path: str | os.PathLike, setting: str) -> BronchoError:
    return BronchoError(f"{setting} {path}: a symbolic link loop (a link that leads back to itself); fix or "
                        "remove the link")


def resolve(path: str | os.PathLike, setting: str, base: Path | None = None) -> Path:
    """``path`` (``~`` expanded, relative to ``base`` when given) with its symlinks followed; one line on a loop."""
    p = Path(path).expanduser()
    if base is not None and not p.is_absolute():
        p = base / p
    try:
        return p.resolve()
    except (RuntimeError, OSError) as exc:
        if is_loop(exc):
            raise loop_error(path, setting) from None
        raise


def _within(path: Path, trees: Sequence[str]) -> bool:
    return any(path == Path(t) or Path(t) in path.parents for t in trees)


def check_writable_root(path: Path, setting: str, configured: str | os.PathLike | None = None) -> None:
    """An output root must not be a system folder (``/``, ``/etc``, a home, ...) nor inside the OS's own trees
    (``/dev/shm`` and the other ``USER_TREES`` are users' folders). Its symlinks are followed: the place written
    is judged. ``configured``: the value as the user wrote it (or the default), named in the line."""
    real = resolve(path, setting)
    inside = _within(real, SYSTEM_TREES) and not _within(real, USER_TREES)
    if str(real) in SYSTEM_FOLDERS or inside or real == Path.home():
        shown = configured if configured is not None else path
        where = "" if str(real) == str(shown) else f" (that is {real})"
        raise BronchoError(f"{setting} {shown}{where}: a system folder; point {setting} at a folder of this "
                           "project (e.g. runs/...)")


def outside(root: str | os.PathLike, paths: Sequence[str]) -> list[int]:
    """Indices of ``paths`` (absolute and normalised) that are not inside ``root`` (lexically: no symlink is read)."""
    prefix = os.path.normpath(os.path.abspath(root)).rstrip(os.sep) + os.sep
    return [i for i, p in enumerate(paths) if not p.startswith(prefix)]


def plain_name(name: str) -> bool:
    """A name that stays in its folder as a file name: no separator, not ``.``/``..``, not empty."""
    return bool(name) and name not in (".", "..") and "/" not in name and "\\" not in name and "\0" not in name


def nearest_existing(path: str | os.PathLike) -> Path:
    """``path`` or its nearest ancestor that exists (where a path to be created would go; whose file system's
    free space a write to it would use)."""
    p = Path(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def mount_point(path: str | os.PathLike) -> Path:
    """The mount point of the file system that holds ``path`` (or its nearest existing ancestor): the file system
    a disk-full line names, with its free space."""
    folder = Path(os.path.abspath(nearest_existing(path)))
    while not os.path.ismount(folder) and folder != folder.parent:
        folder = folder.parent
    return folder


def not_writable(folder: str | os.PathLike) -> str | None:
    """Why nothing can be created in the existing folder ``folder`` ("read-only file system", "permission
    denied"); None: it can."""
    return _why_not_writable(Path(folder))


def sqlite_unwritable(db: Path) -> str | None:
    """Why a SQLite database in write-ahead-log mode cannot be opened, even to read it: its folder is not writable
    (its ``-shm`` index is made there); None when the folder is writable."""
    why = not_writable(db.parent)
    return None if why is None else (
        f"its folder {db.parent} is not writable ({why}); SQLite writes beside the database even to read it (the "
        f"index {db.name}-shm of its write-ahead log): make the folder writable, or copy it somewhere writable")


def _why_not_writable(folder: Path) -> str | None:
    """Why nothing can be created in the existing folder ``folder`` (None: it can)."""
    try:
        if os.statvfs(folder).f_flag & os.ST_RDONLY:
            return "read-only file system"
    except OSError as exc:
        return exc.strerror or str(exc)
    if not os.access(folder, os.W_OK | os.X_OK):
        return "permission denied"
    return None


def check_output(path: Path, setting: str, kind: str = "folder") -> None:
    """``path`` (a ``folder``, or a file to create: ``kind`` names it, e.g. "database file") can be written:
    BronchoError naming ``setting`` otherwise. Creates nothing.

    Refused, one line each: a system folder or a path inside the OS's trees (``check_writable_root``), a symlink
    loop, an existing path of the other kind, a path under a file, a nearest existing folder this user may not
    write in or on a read-only file system.
    """
    check_writable_root(path, setting)
    if path.exists():
        if kind == "folder" and not path.is_dir():
            raise BronchoError(f"{setting} {path}: is a file, not a folder; point {setting} at a folder")
        if kind != "folder" and path.is_dir():
            raise BronchoError(f"{setting} {path}: is a folder, not a {kind}; point {setting} at a file")
        target = path if path.is_dir() else path.parent
        why = _why_not_writable(target)
        if why is not None:
            raise BronchoError(f"{setting} {path}: cannot write there ({why}); point {setting} at a writable place")
        return
    nearest = nearest_existing(path.parent)
    if not nearest.is_dir():
        raise BronchoError(f"{setting} {path}: {nearest} is a file, so no {kind} can be created there")
    why = _why_not_writable(nearest)
    if why is not None:
        raise BronchoError(f"{setting} {path}: cannot create it in {nearest} ({why}); point {setting} at a "
                           "writable place")
