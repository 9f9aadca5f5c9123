"""Database and MLflow URLs: the one parser of ``sqlite:///`` paths, password redaction, driver names."""

from __future__ import annotations

import os
import re
from pathlib import Path

_SQLITE = re.compile(r"^(sqlite(?:\+\w+)?:///)(.+)$")
_PASSWORD = re.compile(r"(://[^:/@\s]+):[^@/\s]*@")


def redact(text: str) -> str:
    """Hide every URL password in ``text`` (``scheme://user:secret@host`` -> ``scheme://user:***@host``)."""
    return _PASSWORD.sub(r"\1:***@", text)


def sqlite_file(url: str) -> Path | None:
    """The database file of a ``sqlite:///path`` URL (None for other URLs and in-memory SQLite)."""
    m = _SQLITE.match(url)
    if not m or m.group(2) in (":memory:", ""):
        return None
    return Path(m.group(2))


def resolve(url: str, base: Path) -> str:
    """Expand ``${VAR}``s and make a relative ``sqlite:///`` path absolute against ``base``."""
    url = os.path.expandvars(url)
    m = _SQLITE.match(url)
    if not m or m.group(2).startswith("/") or m.group(2) == ":memory:":
        return url
    return f"{m.group(1)}{(base / os.path.expanduser(m.group(2))).resolve()}"


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
