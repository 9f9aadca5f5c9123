"""Database and MLflow URLs: the one parser of ``sqlite:///`` paths, password redaction, driver names."""

from __future__ import annotations

import os
import re
import sqlite3
from pathlib import Path

from . import pathcheck
from .errors import BronchoError

_SQLITE = re.compile(r"^(sqlite(?:\+\w+)?:///)(.+)$")
# the forms libpq, SQLAlchemy and MLflow accept: userinfo (``scheme://user:secret@host``, user may be empty) and
# a ``password``/``sslpassword`` parameter (``?password=secret``, ``&password=...``, libpq's ``password='a b'``)
_USERINFO = re.compile(r"(://[^:/@\s'\"]*):[^/?#\s'\"]*@")  # to the last @: a password may hold one
_PARAMETER = re.compile(r"(?i)((?:^|(?<=[\s?&;,(\[{'\"]))(?:ssl)?password\s*=\s*)('(?:[^'\\]|\\.)*'|[^\s&#'\"]*)")
# environment variables whose value is a secret wherever it shows up (libpq, MLflow's HTTP auth)
SECRET_ENV = ("PGPASSWORD", "MLFLOW_TRACKING_PASSWORD", "MLFLOW_TRACKING_TOKEN")
MIN_SECRET = 4  # a shorter stored secret is not hunted for in free text (it would mask ordinary words)
_pgpass_cache: dict[tuple[str, int], tuple[str, ...]] = {}


def _pgpass_passwords() -> tuple[str, ...]:
    """The passwords of libpq's password file (``PGPASSFILE``, else ``~/.pgpass``), read once per change."""
    path = os.environ.get("PGPASSFILE") or os.path.join(os.path.expanduser("~"), ".pgpass")
    try:
        key = (path, os.stat(path).st_mtime_ns)
    except OSError:
        return ()
    if key not in _pgpass_cache:
        found = []
        try:
            lines = Path(path).read_text(errors="replace").splitlines()
        except OSError:
            lines = []
        for line in lines:  # host:port:database:user:password, ``\:`` and ``\\`` escaped
            if line.startswith("#"):
                continue
            fields = re.split(r"(?<!\\):", line, maxsplit=4)
            if len(fields) == 5:
                found.append(fields[4].replace("\\:", ":").replace("\\\\", "\\"))
        _pgpass_cache.clear()
        _pgpass_cache[key] = tuple(found)
    return _pgpass_cache[key]


def known_secrets() -> list[str]:
    """Secrets held outside the config (``PGPASSWORD``, MLflow's password/token, ``.pgpass``), longest first."""
    values = [os.environ.get(name, "") for name in SECRET_ENV] + list(_pgpass_passwords())
    return sorted({v for v in values if len(v) >= MIN_SECRET}, key=len, reverse=True)


def redact(text: str) -> str:
    """Hide every password in ``text``: URL userinfo (``scheme://user:secret@host`` -> ``scheme://user:***@host``),
    ``password=`` parameters (``?password=secret`` -> ``?password=***``), and the literal value of every secret
    held in the environment or libpq's password file (:func:`known_secrets`)."""
    text = _PARAMETER.sub(r"\1***", _USERINFO.sub(r"\1:***@", text))
    for secret in known_secrets():
        text = text.replace(secret, "***")
    return text


def error_line(exc: BaseException, limit: int | None = None) -> str:
    """What a one-line message shows of an exception: its first non-blank line (the database driver's own under
    SQLAlchemy's wrapper, ``exc.orig``), passwords redacted, at most ``limit`` characters; its type when empty."""
    lines = [s for s in str(getattr(exc, "orig", None) or exc).strip().splitlines() if s.strip()]
    return redact(lines[0] if lines else type(exc).__name__)[:limit]


def has_secret(text: str) -> bool:
    """Whether ``text`` holds a password :func:`redact` would hide (a URL or a ``--set`` override)."""
    return redact(text) != text


def sqlite_file(url: str) -> Path | None:
    """The database file of a ``sqlite:///path`` URL (None for other URLs and in-memory SQLite)."""
    m = _SQLITE.match(url)
    if not m or m.group(2) in (":memory:", ""):
        return None
    return Path(m.group(2))


def resolve(url: str, base: Path, setting: str = "url") -> str:
    """Expand ``${VAR}``s (an undefined one is an error naming ``setting``) and make a relative ``sqlite:///``
    path absolute against ``base``."""
    url = pathcheck.expand(url, setting)
    m = _SQLITE.match(url)
    if not m or m.group(2).startswith("/") or m.group(2) == ":memory:":
        return url
    return f"{m.group(1)}{pathcheck.resolve(m.group(2), setting, base)}"


def sqlalchemy(url: str) -> str:
    """``postgres://`` and ``postgresql://`` go through psycopg 3 (the installed driver)."""
    return re.sub(r"^postgres(?:ql)?://", "postgresql+psycopg://", url)


def is_direct_store(url: str) -> bool:
    """True for a store MLflow opens itself (a database or a folder; artifacts go where we say), not a server."""
    return url.startswith(("sqlite:", "file:", "/", "postgresql", "mysql", "mssql")) or "://" not in url


def is_server(url: str) -> bool:
    """True for an MLflow tracking server (``http(s)://``), False for a database or local store."""
    return url.startswith(("http://", "https://", "databricks"))


def is_postgres(url: str) -> bool:
    """True for a PostgreSQL URL (``postgres://``, ``postgresql://``, ``postgresql+driver://``)."""
    return re.match(r"^postgres(?:ql)?(?:\+\w+)?://", url) is not None


# -- a damaged SQLite store: one line naming the file and what to do ----------------------------------------

DAMAGED = ("database disk image is malformed", "file is not a database")
_SQLITE_MAGIC = b"SQLite format 3\x00"
_checked: dict[str, str] = {}  # setting -> the SQLite file this process last opened for it (damaged_message)


# Descriptors of the SQLite files whose header this process has read, by (device, inode), never closed: closing
# *any* descriptor of a file drops every POSIX lock this process holds on it, SQLite's included
# (https://sqlite.org/howtocorrupt.html, 2.2). A header read with open()/close() while this process had a connection
# to the same database (a second store of one sweep, an in-process command) took away the connection's locks;
# another process then saw the database unused, reset its WAL, and a worker's claim and finish were lost (the
# flaky "damaged row" tests of tests/sweep/test_store_faults.py; "disk I/O error" on the next open).
_headers: dict[tuple[int, int], int] = {}


def _header(path: Path) -> bytes:
    """The first 100 bytes of ``path``, read through a descriptor this process keeps open (see ``_headers``)."""
    st = os.stat(path)
    fd = _headers.get((st.st_dev, st.st_ino))
    if fd is None:
        fd = os.open(path, os.O_RDONLY)  # not inherited by child processes (PEP 446)
        opened = os.fstat(fd)  # the file itself, should the path have been replaced since the stat
        _headers[(opened.st_dev, opened.st_ino)] = fd
    return os.pread(fd, 100, 0)


def sqlite_damage(path: Path) -> str | None:
    """Why the SQLite file ``path`` cannot be a sound database, read from its 100-byte header (None: it looks
    sound, is empty or does not exist yet): not SQLite at all, or shorter than the pages its header counts (unless
    its ``-wal`` file holds the rest: ``_wal_makes_whole``)."""
    try:
        size = os.path.getsize(path)
        if size == 0:
            return None  # SQLite treats an empty file as a new database
        head = _header(path)
    except OSError:
        return None  # missing or unreadable: the caller's own checks say so
    if len(head) < 100 or not head.startswith(_SQLITE_MAGIC):
        return "file is not a database"
    page_size = int.from_bytes(head[16:18], "big")
    page_size = 65536 if page_size == 1 else page_size
    pages = int.from_bytes(head[28:32], "big")
    if head[24:28] == head[92:96] and pages and size < pages * page_size:  # the page count is valid: truncated
        if _wal_makes_whole(path):  # WAL mode: the newest pages live in <file>-wal (a checkpoint cut short)
            return None
        return f"database disk image is malformed: {size} bytes, its header counts {pages * page_size}"
    return None


def _wal_makes_whole(path: Path) -> bool:
    """Whether SQLite itself accepts ``path`` together with its ``-wal`` file (``PRAGMA integrity_check`` ok).

    In WAL mode the database file alone may be shorter than its header counts: a checkpoint that a full disk cut
    short wrote page 1 but not the pages after it, which the WAL still holds. Read-only: nothing is checkpointed."""
    try:
        if os.path.getsize(f"{path}-wal") == 0:
            return False
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=1)
        try:
            return db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        finally:
            db.close()
    except (OSError, sqlite3.Error):
        return False


def damaged_sqlite(path: Path | str, setting: str, why: str) -> BronchoError:
    return BronchoError(f"{setting} {path}: damaged SQLite database ({why}); restore it from a backup, or move it "
                        f"aside (mv {path} {path}.damaged) to start a new one; `sqlite3 {path} .recover` may save "
                        "its rows")


def check_sqlite(path: Path, setting: str) -> None:
    """A damaged SQLite file at ``path`` is one line naming ``setting``, the file and what to do."""
    _checked[setting] = str(path)
    why = sqlite_damage(path)
    if why is not None:
        raise damaged_sqlite(path, setting, why)


def damage_in(exc: BaseException) -> str | None:
    """The SQLite damage an exception (or one it wraps) reports: "database disk image is malformed", "file is
    not a database"; None for anything else."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        text = f"{e} {getattr(e, 'orig', '') or ''}".lower()
        found = next((d for d in DAMAGED if d in text), None)
        if found:
            return found
        e = e.__cause__ or e.__context__
    return None


def _fails_quick_check(path: Path) -> bool:
    """Whether SQLite's own ``PRAGMA quick_check`` finds ``path`` damaged (read-only; only after a failure)."""
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=1)
        try:
            return db.execute("PRAGMA quick_check").fetchone()[0] != "ok"
        finally:
            db.close()
    except sqlite3.DatabaseError as exc:
        return damage_in(exc) is not None
    except sqlite3.Error:
        return False


def damaged_message(exc: BaseException) -> str | None:
    """One line for a damaged SQLite store met mid-command (after the header check passed): the store of this
    command that is damaged and what to do; None when ``exc`` is not SQLite damage."""
    why = damage_in(exc)
    if why is None:
        return None
    stores = [(path, setting) for setting, path in _checked.items()]
    damaged = [(p, s) for p, s in stores if sqlite_damage(Path(p)) is not None or _fails_quick_check(Path(p))]
    if len(damaged) == 1:
        return str(damaged_sqlite(damaged[0][0], damaged[0][1], why))
    files = ", ".join(f"{s} {p}" for p, s in (damaged or stores)) or "a SQLite store"
    return (f"damaged SQLite database ({why}) among {files}; run `sqlite3 <file> 'PRAGMA integrity_check'` on "
            "each, restore the damaged one from a backup or move it aside to start a new one")
