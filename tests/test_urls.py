"""Database and MLflow URLs: password redaction, SQLite paths, resolution, driver names."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

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


@pytest.mark.parametrize("text, shown", [
    ("postgresql://bp:s3cr:et@db/x", "postgresql://bp:***@db/x"),  # a colon in the password
    ("postgresql://:s3cret@db/x", "postgresql://:***@db/x"),  # no user name
    ("postgresql://bp:p@ss@db:5432/x", "postgresql://bp:***@db:5432/x"),  # an @ in the password
    ("postgresql://bp@db/x?sslmode=require&password=s3cret", "postgresql://bp@db/x?sslmode=require&password=***"),
    ("postgresql://db/x?password=s3cret&sslmode=require", "postgresql://db/x?password=***&sslmode=require"),
    ("host=db password='s3 cret' dbname=x", "host=db password=*** dbname=x"),  # libpq keyword/value
    ("host=db PASSWORD=s3cret", "host=db PASSWORD=***"),
    ("mysql://u@h/db?sslpassword=s3cret", "mysql://u@h/db?sslpassword=***"),
    ("storage.url=postgresql://db/x?password=s3cret", "storage.url=postgresql://db/x?password=***"),
    ("a passwordless://db/x and password_file=/p", "a passwordless://db/x and password_file=/p"),
])
def test_every_password_form_libpq_and_mlflow_accept_is_redacted(text, shown):
    assert urls.redact(text) == shown and "s3" not in urls.redact(text)
    assert urls.has_secret(text) == (text != shown)


def test_passwords_held_outside_the_config_are_redacted_wherever_they_appear(tmp_path, monkeypatch):
    pgpass = tmp_path / "pgpass"
    pgpass.write_text("# comment\ndb:5432:*:bp:from\\:pgpass\nbad line\n*:*:*:*:abc\n")
    monkeypatch.setenv("PGPASSFILE", str(pgpass))
    monkeypatch.setenv("PGPASSWORD", "from-env-var")
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", "mlflow-pw")
    text = "connection failed for from-env-var / from:pgpass / mlflow-pw (abc stays: too short to hunt)"
    assert urls.redact(text) == "connection failed for *** / *** / *** (abc stays: too short to hunt)"
    pgpass.write_text("db:5432:*:bp:changed-pw\n")
    os.utime(pgpass, ns=(1, 1))  # a new mtime even on a coarse clock: the file is read again
    assert urls.redact("changed-pw") == "***"
