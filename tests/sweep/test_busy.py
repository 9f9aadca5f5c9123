"""A busy MLflow database (issue 22, item 3): `status`, `report` and `sweep` wait runs.busy_timeout_s for a
lock, then print one line and exit 2; a lock released within the bound lets them succeed."""

from __future__ import annotations

import contextlib
import io
import shutil
import sqlite3
import threading
from pathlib import Path

import pytest
from sweep_config import config_in
from sweep_fakes import FAKE
from tinydata import write_tiny_dataset

from bronchocli.cli import main
from bronchocli.config import load_config
from bronchocli.runs.client import MlflowBusy, _open, client_for, retry_busy


@pytest.fixture
def project(make_config, tmp_path):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    return make_config(archs=("baseline",))


@pytest.fixture(scope="module")
def swept_once(tmp_path_factory, mlflow_template) -> Path:
    """A ``project`` whose one-cell fake sweep is done (something for `status` and `report` to show), swept once
    for the module: the tests below lock a copy of it (``swept``)."""
    root = tmp_path_factory.mktemp("swept") / "project"
    root.mkdir()
    write_tiny_dataset(root / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    config_in(root, mlflow_template, archs=("baseline",))
    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        (root.parent / "fake").mkdir()
        mp.setenv("SWEEP_FAKE_DIR", str(root.parent / "fake"))
        mp.setenv("COLUMNS", "200")
        try:  # as the `cli` fixture runs a command (a module fixture cannot use it)
            main(["sweep", "-c", str(root / "experiments.yaml"), *FAKE])
            code = 0
        except SystemExit as exc:
            code = exc.code
    assert code in (0, None), out.getvalue() + err.getvalue()
    return root


@pytest.fixture
def swept(swept_once, tmp_path):
    """A copy of ``swept_once`` (a project copied whole keeps to its own stores: tests/test_relocation.py). The
    databases with their write-ahead logs; SQLite rebuilds a missing ``-shm`` index from the log."""
    copy = tmp_path / "swept"
    shutil.copytree(swept_once, copy, ignore=shutil.ignore_patterns("*-shm"))
    cfg = load_config(copy / "experiments.yaml")
    client_for(cfg)  # opened once before any lock: the copy's artifact locations rewritten to its own folder
    return cfg


class Lock:
    """An exclusive lock on a SQLite file, held by another connection (what a long writer elsewhere does)."""

    def __init__(self, db) -> None:
        self.conn = sqlite3.connect(db, isolation_level=None, check_same_thread=False)
        self.conn.execute("BEGIN EXCLUSIVE")
        self.held = True

    def release(self) -> None:
        if self.held:
            self.conn.execute("ROLLBACK")
            self.held = False
        self.conn.close()


def release_when_the_command_reaches_the_store(monkeypatch, lock: Lock) -> list[bool]:
    """Release ``lock`` from a thread as the command starts its first store request (still locked then)."""
    real, seen = _open, []

    def opening(uri):
        seen.append(lock.held)
        threading.Timer(0.2, lock.release).start()
        return real(uri)

    monkeypatch.setattr("bronchocli.runs.client._open", opening)
    return seen


COMMANDS = {
    "status": ["status"],
    "report": ["report", "--table", "personalized", "-q", "--out", "{out}"],
    "sweep": ["sweep", "--workers", "1", *FAKE],
}


def args(command, project) -> list[str]:
    return [a.format(out=project.paths.base / "reports") for a in COMMANDS[command]]


@pytest.mark.parametrize("command", list(COMMANDS))
def test_a_locked_store_is_waited_for_then_one_line_and_exit_2(cli, project, swept, fake_dir, command):
    project = project if command == "sweep" else swept  # swept: something to show
    path = str(project.paths.base / "experiments.yaml")
    lock = Lock(project.paths.base / "mlflow.db")
    try:
        code, out, err = cli(*args(command, project), "-c", path, "--set", "runs.busy_timeout_s=0.5")
    finally:
        lock.release()
    assert code == 2, out + err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err + out
    assert "busy or unavailable for 0.5 s" in err and "database is locked" in err and "busy_timeout_s" in err


@pytest.mark.parametrize("command", list(COMMANDS))
def test_a_lock_released_within_the_bound_lets_the_command_succeed(cli, project, swept, fake_dir, monkeypatch,
                                                                   command):
    project = project if command == "sweep" else swept
    path = str(project.paths.base / "experiments.yaml")
    lock = Lock(project.paths.base / "mlflow.db")
    seen = release_when_the_command_reaches_the_store(monkeypatch, lock)
    try:
        code, out, err = cli(*args(command, project), "-c", path, "--set", "runs.busy_timeout_s=60")
    finally:
        lock.release()
    assert code == 0, out + err
    assert seen and seen[0] is True  # the store was locked when the command first reached it


def test_transient_errors_are_retried_and_others_are_not():
    calls = []

    def flaky():
        calls.append(1)
        if len(calls) < 3:
            raise RuntimeError("(psycopg.OperationalError) server closed the connection unexpectedly")
        return "ok"

    assert retry_busy(flaky, "test", 30, "db") == "ok" and len(calls) == 3
    with pytest.raises(ValueError):
        retry_busy(lambda: (_ for _ in ()).throw(ValueError("no such column")), "test", 30, "db")
    with pytest.raises(MlflowBusy, match="during test"):
        retry_busy(lambda: (_ for _ in ()).throw(RuntimeError("database is locked")), "test", 0.01, "db")


def test_a_locked_claims_database_is_waited_for_then_one_line_and_exit_2(cli, swept, fake_dir):
    project = swept  # swept: the claims table exists (WAL: readers pass, writers wait)
    path = str(project.paths.base / "experiments.yaml")
    lock = Lock(project.paths.base / "sweep.db")
    try:
        code, out, err = cli("sweep", "-c", path, "--retry-failed", "--set", "runs.busy_timeout_s=0.5", *FAKE)
    finally:
        lock.release()
    assert code == 2 and len(err.strip().splitlines()) == 1, out + err
    assert "sweep storage" in err and "database is locked" in err and "Traceback" not in out + err
