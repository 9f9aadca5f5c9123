"""Fixtures of the sweep tests: configs on temp stores (MLflow's copied from tests/conftest.py's template), fake
runners, PostgreSQL schemas."""

from __future__ import annotations

import sys
import uuid
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
PG_BASE = "postgresql+psycopg://postgres@127.0.0.1:5432/test"

if str(HERE) not in sys.path:  # spawned workers inherit sys.path: they can import sweep_fakes
    sys.path.insert(0, str(HERE))

from sweep_config import config_in  # noqa: E402


@pytest.fixture
def fake_dir(tmp_path, monkeypatch) -> Path:
    """The fake runner's control folder (spawned and Slurm-started workers inherit it through the environment).

    A sweep runs the fake when given it: ``--runner sweep_fakes:fake_runner`` (``sweep_fakes.FAKE``) on the
    command line, ``runner=fake_runner`` in a library call."""
    d = tmp_path / "fake"
    d.mkdir()
    monkeypatch.setenv("SWEEP_FAKE_DIR", str(d))
    return d


@pytest.fixture
def make_config(tmp_path, mlflow_template):
    """``config_in(tmp_path, ...)``: an experiments.yaml in tmp_path (MLflow store copied from the template),
    loaded."""

    def make(*args, **kw):
        return config_in(tmp_path, mlflow_template, *args, **kw)

    return make


def _pg_admin():
    """An autocommit connection to the database ``test`` of the local PostgreSQL server; skips without one."""
    psycopg = pytest.importorskip("psycopg")
    try:
        return psycopg.connect(host="127.0.0.1", port=5432, user="postgres", dbname="test", connect_timeout=3,
                               autocommit=True)
    except psycopg.Error as exc:
        pytest.skip(f"PostgreSQL at 127.0.0.1:5432/test unreachable: {exc}")


@pytest.fixture
def pg_url():
    """A fresh schema in the PostgreSQL database ``test`` (dropped afterwards); skips if no server."""
    conn = _pg_admin()
    schema = f"sweep_{uuid.uuid4().hex[:10]}"
    conn.execute(f"CREATE SCHEMA {schema}")
    try:
        yield f"{PG_BASE}?options=-csearch_path%3D{schema}"
    finally:
        conn.execute(f"DROP SCHEMA {schema} CASCADE")
        conn.close()


@pytest.fixture
def fresh_db():
    """A new, empty PostgreSQL database (dropped afterwards): nothing of MLflow's schema exists yet."""
    conn = _pg_admin()
    name = f"fresh_{uuid.uuid4().hex[:10]}"
    conn.execute(f"CREATE DATABASE {name}")
    try:
        yield f"postgresql://postgres@127.0.0.1:5432/{name}"
    finally:
        conn.execute(f"DROP DATABASE {name} WITH (FORCE)")
        conn.close()
