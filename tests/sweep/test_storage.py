"""The claims table's transitions on SQLite and on the real PostgreSQL: exclusive claims, tokens, staleness."""

from __future__ import annotations

import time

import pytest
from sqlalchemy import update

from bronchocli.config import Config, expand_grid
from bronchocli.errors import BronchoError
from bronchocli.sweep.storage import FAILED, FINISHED, PENDING, RUNNING, SweepStore, cells_table
from bronchocli.urls import sqlalchemy as normalize_url

CFG = Config.model_validate({"name": "t", "grid": {"arch": ["baseline", "lstm", "conv3d"], "rot_loss": ["mse"],
                                                   "population": ["personalized"], "seed": [0]}})
CELLS = expand_grid(CFG)
KEYS = [c.key for c in CELLS]


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def store(request, tmp_path):
    url = f"sqlite:///{tmp_path}/sweep.db" if request.param == "sqlite" else request.getfixturevalue("pg_url")
    s = SweepStore(url)
    s.ensure_schema()
    s.add_cells("t", CELLS)
    yield s
    s.close()


def claim(store, worker="w1", max_retries=1, stale=60.0, keys=KEYS):
    return store.claim("t", keys, worker, max_retries=max_retries, stale_after_s=stale)


def backdate(store, key, seconds=1000.0):
    """Make a claim look abandoned: its heartbeat goes back in time (what a dead worker leaves)."""
    with store.engine.begin() as conn:
        conn.execute(update(cells_table).where(cells_table.c.cell_key == key)
                     .values(heartbeat=cells_table.c.heartbeat - seconds))


def state(store, key):
    return next(r for r in store.rows("t") if r.cell_key == key)


def test_each_cell_is_claimed_once_in_grid_order_and_only_the_holder_records_it(store):
    claims = [claim(store, f"w{i}") for i in range(3)]
    assert [c.row.cell_key for c in claims] == KEYS
    assert claim(store, "w9") is None  # all taken, none stale
    a = claims[0]
    assert not store.finish("not-a-token", "run-y", 1.0)
    assert store.finish(a.token, "run-a", 2.5)
    assert not store.finish(a.token, "run-a2", 1.0)  # a finished claim is not running any more
    row = state(store, KEYS[0])
    assert (row.state, row.run_id, row.duration_s, row.attempts, row.token) == (FINISHED, "run-a", 2.5, 1, a.token)
    assert not store.all_done("t", KEYS, 1)
    assert store.all_done("t", KEYS[:1], 1)


def test_add_cells_is_idempotent_and_keeps_state(store):
    c = claim(store)
    store.finish(c.token, "r", 1.0)
    assert store.add_cells("t", CELLS) == 0
    assert len(store.rows("t")) == 3 and state(store, KEYS[0]).state == FINISHED
    other = Config.model_validate({**CFG.model_dump(mode="json"), "train": {"lr": 0.5}})
    new = expand_grid(other)
    assert not {x.key for x in new} & set(KEYS)  # a changed run config makes new cells...
    assert store.add_cells("t", new) == 3  # ...stored beside the old ones, never reusing them
    assert {r.state for r in store.rows("t", [x.key for x in new])} == {PENDING}


def test_a_stale_claim_is_taken_over_and_the_old_holder_can_no_longer_write(store):
    first = claim(store, "dead", keys=KEYS[:1])
    assert claim(store, "w2", keys=KEYS[:1], stale=2.0) is None
    backdate(store, KEYS[0])
    second = claim(store, "w2", keys=KEYS[:1], stale=2.0)
    assert second is not None and second.previous.token == first.token and second.previous.worker == "dead"
    assert not second.exhausted and second.row.attempts == 2
    assert not store.heartbeat(first.token) and not store.set_run_id(first.token, "orphan")
    assert not store.finish(first.token, "orphan", 1.0)
    assert store.heartbeat(second.token) and store.finish(second.token, "good", 1.0)
    assert state(store, KEYS[0]).run_id == "good"


def test_a_heartbeat_keeps_a_claim_from_being_taken(store):
    first = claim(store, "slow", keys=KEYS[:1])
    backdate(store, KEYS[0])
    assert store.heartbeat(first.token)
    assert claim(store, "w2", keys=KEYS[:1], stale=2.0) is None


def test_lost_workers_use_up_attempts(store):
    claim(store, "dead", keys=KEYS[:1], max_retries=0)
    backdate(store, KEYS[0])
    c = claim(store, "w2", keys=KEYS[:1], max_retries=0, stale=2.0)
    assert c.exhausted and c.row.attempts == 1  # to be marked failed by its new holder, not run
    assert store.fail(c.token, "worker dead lost")
    assert claim(store, "w3", keys=KEYS[:1], max_retries=0) is None
    assert store.all_done("t", KEYS[:1], 0)


def test_failed_cells_retry_up_to_max_retries_then_reset(store):
    for attempt in (1, 2):
        c = claim(store, keys=KEYS[:1], max_retries=1)
        assert c.row.attempts == attempt
        assert store.fail(c.token, f"boom {attempt}", "run")
    assert claim(store, keys=KEYS[:1], max_retries=1) is None
    row = state(store, KEYS[0])
    assert (row.state, row.attempts, row.failure_reason) == (FAILED, 2, "boom 2")
    assert store.all_done("t", KEYS[:1], 1) and not store.all_done("t", KEYS[:1], 2)
    assert store.reset_failed("t", KEYS) == 1
    assert claim(store, keys=KEYS[:1], max_retries=0).row.attempts == 1


def test_release_gives_the_cell_back_without_using_an_attempt(store):
    c = claim(store, keys=KEYS[:1])
    assert c.released_run is None and store.set_run_id(c.token, "killed-run")
    assert store.release(c.token)
    row = state(store, KEYS[0])
    assert (row.state, row.attempts, row.token, row.worker) == (PENDING, 0, None, None)
    again = claim(store, keys=KEYS[:1], max_retries=0)
    assert again.row.attempts == 1 and state(store, KEYS[0]).state == RUNNING
    assert again.released_run == "killed-run"  # the worker may resume that run
    assert store.fail(again.token, "boom", "failed-run")
    # A failed run is offered too: the worker resumes it only when the machine failed it (disk full, busy database).
    assert claim(store, keys=KEYS[:1], max_retries=1).released_run == "failed-run"
    assert store.release(claim(store, keys=KEYS[1:2]).token, "MlflowBusy: database is locked")
    assert state(store, KEYS[1]).failure_reason == "MlflowBusy: database is locked"  # the reason stays visible


def test_database_clock_is_epoch_seconds(store):
    assert abs(store.db_now() - time.time()) < 60  # unit/epoch check, not a timing check


def test_urls_are_normalised_and_errors_hide_passwords():
    assert normalize_url("postgresql://u:p@h/db") == "postgresql+psycopg://u:p@h/db"
    assert normalize_url("postgres://h/db") == "postgresql+psycopg://h/db"
    assert normalize_url("sqlite:///x.db") == "sqlite:///x.db"
    store = SweepStore("postgresql://alice:hunter2@127.0.0.1:1/nowhere")
    assert store.redacted == "postgresql+psycopg://alice:***@127.0.0.1:1/nowhere"
    with pytest.raises(BronchoError) as exc:
        store.ensure_schema()
    assert "hunter2" not in str(exc.value) and "alice:***@" in str(exc.value)


def wal_cut_short(db, snap):
    """``snap``: the claims database ``db`` as a full disk leaves it in WAL mode (issue 37.3): the rows live in
    ``snap``-wal, and a checkpoint wrote page 1 (the header counting every page) but none of the pages after it."""
    import shutil
    import sqlite3

    store = SweepStore(f"sqlite:///{db}")
    store.ensure_schema()  # WAL mode from its first connection on
    hold = sqlite3.connect(db, isolation_level=None)  # another process's connection: no checkpoint on close
    hold.execute("PRAGMA wal_autocheckpoint = 0")
    hold.execute(f"SELECT count(*) FROM {cells_table.name}").fetchone()
    store.add_cells("t", CELLS)
    store.close()
    shutil.copy(db, snap)
    shutil.copy(f"{db}-wal", f"{snap}-wal")  # the rows are here, not yet in the database file
    hold.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    hold.close()
    page_size = int.from_bytes(db.read_bytes()[16:18], "big")
    snap.write_bytes(db.read_bytes()[:page_size])  # the checkpoint's first page written, then the disk was full
    return snap


def test_a_database_whose_wal_holds_the_rest_is_not_damaged_but_one_without_it_is(tmp_path):
    import os
    import sqlite3

    from bronchocli.urls import sqlite_damage

    (tmp_path / "ok").mkdir()
    snap = wal_cut_short(tmp_path / "sweep.db", tmp_path / "ok" / "sweep.db")
    header_pages = int.from_bytes(snap.read_bytes()[28:32], "big")
    assert header_pages > 1 and snap.stat().st_size < header_pages * 4096  # the file alone is short
    with sqlite3.connect(f"file:{snap}?mode=ro", uri=True) as ref:  # SQLite's own verdict: sound
        assert ref.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    assert sqlite_damage(snap) is None
    store = SweepStore(f"sqlite:///{snap}")  # opens, and every row is there
    assert [r.cell_key for r in store.rows("t")] == KEYS and claim(store) is not None
    store.close()

    (tmp_path / "bad").mkdir()
    lost = wal_cut_short(tmp_path / "again.db", tmp_path / "bad" / "sweep.db")
    os.remove(f"{lost}-wal")  # the same file without the WAL that completes it: damaged, one line
    assert "header counts" in sqlite_damage(lost)
    with pytest.raises(BronchoError, match="damaged SQLite database"):
        SweepStore(f"sqlite:///{lost}")


_PROBE = """import sqlite3, sys
db = sqlite3.connect(sys.argv[1], timeout=0, isolation_level=None)
try:
    db.execute("BEGIN IMMEDIATE"); db.execute("ROLLBACK"); print("free")
except sqlite3.OperationalError as exc:
    print(exc)
db.close()
"""


def _other_process(db) -> str:
    """What another process finds: "free" (it took the write lock), else SQLite's reason; it then closes."""
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-c", _PROBE, str(db)], capture_output=True, text=True,
                          check=True).stdout.strip()


@pytest.mark.parametrize("journal", ["delete", "wal"])
def test_the_damage_check_leaves_this_processs_sqlite_locks_in_place(tmp_path, journal):
    """Reading a store's header (``urls.sqlite_damage``, run by every store a process opens) must not take away the
    locks of this process's own connections to the same file: closing any descriptor of a file drops every POSIX
    lock the process holds on it (sqlite.org/howtocorrupt.html, 2.2). It once read the file with open()/close():
    in a rollback-journal database another process then took the write lock in the middle of this process's
    transaction; in a WAL database another process closing found itself the last connection and deleted the WAL
    under this process's open one (how a worker's claim and finish were lost in the "damaged row" tests of
    test_store_faults.py, "disk I/O error" on the next open)."""
    import sqlite3
    from pathlib import Path

    from bronchocli.urls import sqlite_damage

    db = tmp_path / "store.db"
    holder = sqlite3.connect(db, isolation_level=None)
    holder.execute(f"PRAGMA journal_mode = {journal}")
    holder.execute("CREATE TABLE t (x)")
    holder.execute("INSERT INTO t VALUES (1)")
    try:
        if journal == "delete":
            holder.execute("BEGIN EXCLUSIVE")  # this process holds the database's write lock
            assert _other_process(db) == "database is locked"  # the probe sees it
            assert sqlite_damage(db) is None and sqlite_damage(db) is None
            assert _other_process(db) == "database is locked"  # still held
            holder.execute("ROLLBACK")
            assert _other_process(db) == "free"  # the probe can tell a free database
        else:
            wal = Path(f"{db}-wal")
            holder.execute("SELECT count(*) FROM t").fetchone()
            assert wal.exists() and _other_process(db) == "free" and wal.exists()  # not the last connection
            assert sqlite_damage(db) is None and sqlite_damage(db) is None
            assert _other_process(db) == "free"
            assert wal.exists()  # the other process still saw this one's connection: it left the WAL alone
            holder.execute("INSERT INTO t VALUES (2)")
            assert holder.execute("SELECT count(*) FROM t").fetchone()[0] == 2
    finally:
        holder.close()
    if journal == "wal":  # the last connection closed: now the other process is the last one and tidies up
        assert _other_process(db) == "free" and not Path(f"{db}-wal").exists()
