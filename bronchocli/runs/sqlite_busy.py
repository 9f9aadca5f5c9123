"""SQLite stores of MLflow wait ``runs.busy_timeout_s`` on a lock instead of MLflow's fixed 20 s.

MLflow opens its own SQLAlchemy engine and sets ``PRAGMA busy_timeout = 20000`` on every session; the
listeners below replace it with this process's bound for the files registered with ``set_busy_timeout``.
SQLite's busy handler is itself a bounded retry, so one attempt waits the whole bound.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, event
from sqlalchemy.pool import Pool

_sqlite_busy_ms: dict[str, int] = {}  # MLflow SQLite files of this process -> their busy timeout


def set_busy_timeout(db: Path, bound_s: float) -> None:
    """Every connection of this process to the SQLite file ``db`` waits up to ``bound_s`` on a lock."""
    _sqlite_busy_ms[str(Path(db).resolve())] = max(1, int(bound_s * 1000))


def _set_sqlite_busy(dbapi_conn: Any, _record: Any, *_proxy: Any) -> None:
    """Every new SQLite connection to one of this process's MLflow stores waits runs.busy_timeout_s on a lock.

    MLflow opens its own engine; SQLite's busy handler is itself a bounded retry, so one attempt waits the bound.
    """
    if not _sqlite_busy_ms or not isinstance(dbapi_conn, sqlite3.Connection):
        return
    try:
        files = {row[2] for row in dbapi_conn.execute("PRAGMA database_list").fetchall()}
        ms = max((_sqlite_busy_ms.get(str(Path(f).resolve()), 0) for f in files if f), default=0)
        if ms:
            dbapi_conn.execute(f"PRAGMA busy_timeout = {int(ms)}")
    except sqlite3.Error:  # the database is locked even for this: the store's own timeout applies
        pass


def _rewrite_busy_pragma(conn: Any, _cursor: Any, statement: str, parameters: Any, *_rest: Any) -> tuple[str, Any]:
    """MLflow sets ``PRAGMA busy_timeout = 20000`` on every session: ours (runs.busy_timeout_s) replaces it."""
    if _sqlite_busy_ms and statement.lstrip().upper().startswith("PRAGMA BUSY_TIMEOUT"):
        db = conn.engine.url.database
        ms = _sqlite_busy_ms.get(str(Path(db).resolve())) if db else None
        if ms:
            return f"PRAGMA busy_timeout = {int(ms)}", parameters
    return statement, parameters


event.listen(Pool, "connect", _set_sqlite_busy)
event.listen(Pool, "checkout", _set_sqlite_busy)  # pooled connections follow the bound of the current config
event.listen(Engine, "before_cursor_execute", _rewrite_busy_pragma, retval=True)
