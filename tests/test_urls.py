"""Database and MLflow URLs: password redaction, SQLite paths, resolution, driver names."""

from __future__ import annotations

from pathlib import Path

from bronchocli import urls


def test_passwords_are_redacted_from_urls():
    assert urls.redact("postgresql+psycopg://bp:s3cret@db.example:5432/sweeps") == (
        "postgresql+psycopg://bp:***@db.example:5432/sweeps")
    assert urls.redact("sqlite:////tmp/x.db") == "sqlite:////tmp/x.db"
    assert urls.redact("http://host:5000") == "http://host:5000"
    text = "tracking: {uri: 'postgresql://a:pw1@h/db'}\nstorage: {url: 'mysql://b:pw2@h:3306/s'}\n"
    assert urls.redact(text) == "tracking: {uri: 'postgresql://a:***@h/db'}\nstorage: {url: 'mysql://b:***@h:3306/s'}\n"


def test_sqlite_file():
    assert urls.sqlite_file("sqlite:////tmp/x.db") == Path("/tmp/x.db")
    assert urls.sqlite_file("sqlite+pysqlite:///rel/x.db") == Path("rel/x.db")
    assert urls.sqlite_file("sqlite:///:memory:") is None
    assert urls.sqlite_file("postgresql://u@h/db") is None


def test_resolve_makes_relative_sqlite_paths_absolute_and_expands_variables(tmp_path, monkeypatch):
    monkeypatch.setenv("PGPASS", "pw")
    assert urls.resolve("sqlite:///runs/x.db", tmp_path) == f"sqlite:///{tmp_path}/runs/x.db"
    assert urls.resolve("sqlite:////abs/x.db", tmp_path) == "sqlite:////abs/x.db"
    assert urls.resolve("sqlite:///:memory:", tmp_path) == "sqlite:///:memory:"
    assert urls.resolve("postgresql://u:${PGPASS}@h/db", tmp_path) == "postgresql://u:pw@h/db"


def test_driver_names_and_servers():
    assert urls.sqlalchemy("postgres://u@h/db") == "postgresql+psycopg://u@h/db"
    assert urls.sqlalchemy("postgresql://u@h/db") == "postgresql+psycopg://u@h/db"
    assert urls.sqlalchemy("sqlite:///x.db") == "sqlite:///x.db"
    assert urls.is_server("http://h:5000") and urls.is_server("https://h")
    assert not urls.is_server("sqlite:///x.db") and not urls.is_server("postgresql://u@h/db")
