"""The claims table: one row per (sweep, cell key) in the SQL database of ``storage.url``.

Every state change is one short transaction whose UPDATE is conditional on
what the writer read (``version``) and on the claimability predicate,
re-evaluated by the database at write time; the UPDATE's row count tells the
writer whether it won. On PostgreSQL the candidate row is also locked with
``SELECT ... FOR UPDATE SKIP LOCKED`` so concurrent claimers pick different
cells instead of queueing on one; on SQLite write transactions start with
``BEGIN IMMEDIATE`` (one writer at a time, WAL so readers never block) and
wait on a busy timeout. Claim, finish, fail, release and heartbeat all carry
the claim's random ``token``: a worker whose claim was taken over can no
longer change the row. Heartbeats and the stale cut-off use the database
server's clock, so workers on machines with skewed clocks agree.
See docs/sweep.md for why this gives exactly one FINISHED run per cell.
"""

from __future__ import annotations

import json
import math
import uuid
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from sqlalchemy import (
    Column,
    Connection,
    Engine,
    Float,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    and_,
    create_engine,
    event,
    inspect,
    literal_column,
    or_,
    select,
    update,
)
from sqlalchemy.exc import DBAPIError, IntegrityError, OperationalError, ProgrammingError, SQLAlchemyError

from .. import extras, pathcheck, urls
from ..cells import Cell
from ..errors import BronchoError
from ..retry import disk_full, disk_full_line, retry

TABLE = "bronchopose_sweep_cells"
SELECTIONS = "bronchopose_sweep_selections"
PENDING, RUNNING, FINISHED, FAILED = "pending", "running", "finished", "failed"
STATES = (PENDING, RUNNING, FINISHED, FAILED)
TAG_CLAIM = "sweep_claim"  # MLflow tag: the claim token a run was made under (finds orphans of a lost worker)
SQLITE_BUSY_MS = 60_000

metadata = MetaData()
cells_table = Table(
    TABLE, metadata,
    Column("sweep", String(200), primary_key=True),
    Column("cell_key", String(64), primary_key=True),
    Column("ord", Integer, nullable=False),  # position in the grid: claim order
    Column("label", String(300), nullable=False),
    Column("coords", Text, nullable=False),  # JSON of Cell.coords()
    Column("state", String(16), nullable=False, default=PENDING),
    Column("attempts", Integer, nullable=False, default=0),  # claims not given back by a clean release
    Column("version", Integer, nullable=False, default=0),  # bumped by every state change
    Column("worker", String(300)),  # host:pid of the claim holder
    Column("token", String(32)),  # random id of the current claim
    Column("heartbeat", Float),  # database epoch seconds
    Column("claimed_at", Float),
    Column("finished_at", Float),
    Column("created_at", Float),
    Column("run_id", String(64)),  # MLflow run of the current/last attempt
    Column("failure_reason", Text),
    Column("duration_s", Float),  # time inside the runner
)
# A staged sweep's selections: written once per (sweep, plan, stage) by whichever process gets there first.
selections_table = Table(
    SELECTIONS, metadata,
    Column("sweep", String(200), primary_key=True),
    Column("plan_key", String(64), primary_key=True),  # hash of the config's run settings and stages
    Column("stage", String(200), primary_key=True),
    Column("selection", Text, nullable=False),  # JSON: by, top, over, source, ranked, selected
    Column("created_at", Float),
)


@dataclass(frozen=True)
class CellRow:
    sweep: str
    cell_key: str
    ord: int
    label: str
    coords: dict[str, Any]
    state: str
    attempts: int
    version: int
    worker: str | None
    token: str | None
    heartbeat: float | None
    claimed_at: float | None
    finished_at: float | None
    created_at: float | None
    run_id: str | None
    failure_reason: str | None
    duration_s: float | None
    damage: str | None = None  # what makes the row unusable (``row_damage``): such a row is neither claimed nor run

    @classmethod
    def from_mapping(cls, m: Any) -> CellRow:
        """The row as stored; a row this code cannot use (changed by hand or by another tool) is read all the same,
        with ``damage`` saying what is wrong and safe values in the damaged columns, so it never stops the others."""
        data = dict(m)
        problems = []
        try:
            coords = json.loads(data["coords"])
            if not isinstance(coords, dict):
                raise ValueError("not a JSON object")
        except (TypeError, ValueError) as exc:
            problems.append(f"coords {str(data['coords'])[:60]!r} is not a JSON object ({str(exc)[:80]})")
            coords = {}
        data["coords"] = coords
        if data["state"] not in STATES:
            problems.append(f"state {str(data['state'])[:40]!r} is not one of {', '.join(STATES)}")
        for col in ("ord", "attempts", "version"):
            if not isinstance(data[col], int) or isinstance(data[col], bool):
                problems.append(f"{col} {str(data[col])[:40]!r} is not a whole number")
                data[col] = 0
        for col in ("heartbeat", "claimed_at", "finished_at", "created_at", "duration_s"):
            v = data[col]
            if v is not None and (not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v)):
                problems.append(f"{col} {str(v)[:40]!r} is not a number of seconds")
                data[col] = None
        return cls(**data, damage="; ".join(problems) or None)

    def retryable(self, max_retries: int) -> bool:
        return self.state == FAILED and self.attempts <= max_retries


@dataclass(frozen=True)
class Claim:
    """A won claim. ``previous`` is the row as it was when it was taken from a lost worker;
    ``exhausted`` means that cell used up its attempts: settle it and mark it failed, do not run it;
    ``released_run`` is the last run of a cell given back (Ctrl-C, busy database), failed with retries left or
    left by a lost worker (a candidate for resuming: the worker decides from the run's status and reason)."""

    row: CellRow
    token: str
    previous: CellRow | None = None
    exhausted: bool = False
    released_run: str | None = None


class SweepStore:
    """The claims table of one storage URL (one engine per process)."""

    def __init__(self, url: str, timeout_s: float = 10.0, busy_timeout_s: float = SQLITE_BUSY_MS / 1000):
        """``timeout_s``: connecting to a database server gives up after this long (runs.timeout_s);
        ``busy_timeout_s``: how long a locked SQLite database is waited for (runs.busy_timeout_s)."""
        self.url = urls.sqlalchemy(url)
        self.redacted = urls.redact(self.url)
        if self.url.startswith("sqlite") and (":memory:" in self.url or self.url.rstrip("/").endswith(":")):
            raise BronchoError(f"storage.url {self.redacted}: an in-memory SQLite database cannot be shared by "
                               "workers; use a file (sqlite:///runs/sweep.db) or postgresql://...")
        if urls.is_postgres(self.url):
            extras.require("postgres", f"storage.url {self.redacted}")
        if (db := urls.sqlite_file(self.url)) is not None:
            urls.check_sqlite(db, "storage.url")  # a damaged file: one line naming it and what to do
        try:
            self.engine: Engine = _make_engine(self.url, timeout_s, busy_timeout_s)
        except (SQLAlchemyError, ImportError, ValueError) as exc:
            raise BronchoError(f"storage.url {self.redacted}: {urls.error_line(exc)}") from None
        self.dialect = self.engine.dialect.name
        self._now = literal_column(_now_sql(self.dialect), Float)

    # -- transactions ------------------------------------------------------------
    @contextmanager
    def _tx(self, write: bool = False) -> Iterator[Connection]:
        try:
            with self.engine.connect() as conn:
                conn = conn.execution_options(sweep_write=write)
                with conn.begin():
                    yield conn
        except (OperationalError, ProgrammingError, DBAPIError) as exc:
            if isinstance(exc, IntegrityError):
                raise
            if (why := urls.damage_in(exc)) and (db := urls.sqlite_file(self.url)) is not None:
                raise urls.damaged_sqlite(db, "storage.url", why) from None  # not an outage: never waited out
            raise StorageError(self._problem(exc)) from None

    def close(self) -> None:
        self.engine.dispose()

    def _problem(self, exc: BaseException) -> str:
        if (full := disk_full(exc)) is not None:  # one line naming the folder, not SQLAlchemy's SQL and parameters
            where = full[1] or urls.sqlite_file(self.url)
            place = disk_full_line(where, full[0]) if where else f"the database server's disk is full ({full[0]})"
            return f"sweep storage {self.redacted}: {place}; free space there and run the same command again"
        if (db := urls.sqlite_file(self.url)) and (line := pathcheck.sqlite_unwritable(db)):  # read-only runs/
            return f"sweep storage {self.redacted}: {line} and point storage.url there"
        text = f"sweep storage {self.redacted}: {urls.error_line(exc)}"
        if self.dialect != "sqlite" and "connect" in text.lower():  # a server that is down, elsewhere or misnamed
            text += "; check the host, port, database name and credentials, and that the server is running"
        return text

    # -- schema ------------------------------------------------------------------
    def exists(self) -> bool:
        if (db := urls.sqlite_file(self.url)) is not None and not db.exists():  # none created just to look
            return False
        try:
            with self.engine.connect() as conn:
                return inspect(conn).has_table(TABLE)
        except SQLAlchemyError as exc:
            raise StorageError(self._problem(exc)) from None

    def ensure_schema(self) -> None:
        """Create the table if missing; tolerate another machine creating it at the same moment."""
        db = urls.sqlite_file(self.url)
        if db is not None:
            db.parent.mkdir(parents=True, exist_ok=True)
        def create() -> None:
            try:
                metadata.create_all(self.engine, checkfirst=True)
            except SQLAlchemyError:
                if not self.exists():  # else another machine created it at the same moment: done
                    raise

        retry(create, transient=lambda e: isinstance(e, SQLAlchemyError), what="creating the claims table",
              attempts=5, first_delay_s=0.2, quiet=True, give_up=lambda e: StorageError(self._problem(e)))

    def db_now(self) -> float:
        with self._tx() as conn:
            return float(conn.execute(select(self._now)).scalar_one())

    # -- planning ----------------------------------------------------------------
    def add_cells(self, sweep: str, cells: Sequence[Cell]) -> int:
        """Insert the rows that are missing (idempotent, safe against concurrent planners); returns how many."""
        existing = {r.cell_key for r in self.rows(sweep, [c.key for c in cells])}
        added = 0
        for ord_, cell in enumerate(cells):
            if cell.key in existing:
                continue
            values = dict(sweep=sweep, cell_key=cell.key, ord=ord_, label=cell.label, coords=json.dumps(cell.coords()),
                          state=PENDING, attempts=0, version=0)
            try:
                with self._tx(write=True) as conn:
                    conn.execute(cells_table.insert().values(**values, created_at=self._now))
                added += 1
            except IntegrityError:  # another planner inserted it first
                pass
        return added

    def rows(self, sweep: str, keys: Sequence[str] | None = None) -> list[CellRow]:
        q = select(cells_table).where(cells_table.c.sweep == sweep).order_by(cells_table.c.ord, cells_table.c.cell_key)
        if keys is not None:
            q = q.where(cells_table.c.cell_key.in_(list(keys)))
        with self._tx() as conn:
            return [CellRow.from_mapping(m) for m in conn.execute(q).mappings()]

    def sweeps(self) -> list[str]:
        with self._tx() as conn:
            return sorted(conn.execute(select(cells_table.c.sweep).distinct()).scalars())

    def reset_failed(self, sweep: str, keys: Sequence[str]) -> int:
        """``--retry-failed``: failed cells back to pending with a fresh attempt budget."""
        c = cells_table.c
        with self._tx(write=True) as conn:
            res = conn.execute(
                update(cells_table)
                .where(c.sweep == sweep, c.cell_key.in_(list(keys)), c.state == FAILED)
                .values(state=PENDING, attempts=0, version=c.version + 1, token=None, worker=None, run_id=None)
            )
            return res.rowcount

    def repair(self, row: CellRow, label: str | None = None, coords: dict[str, Any] | None = None) -> bool:
        """``status --repair`` of a damaged row (as read): pending again, its attempts, claim and run forgotten
        (a FINISHED MLflow run of the cell is recorded again by the next sweep: ``record.rebuild``); ``label`` and
        ``coords`` (the plan's cell) replace damaged ones. False when the row changed since it was read."""
        c = cells_table.c
        values: dict[str, Any] = dict(state=PENDING, attempts=0, version=row.version + 1, token=None, worker=None,
                                      heartbeat=None, claimed_at=None, finished_at=None, run_id=None,
                                      failure_reason=None, duration_s=None, ord=row.ord, created_at=row.created_at)
        if coords is not None:
            values.update(coords=json.dumps(coords), label=label or row.label)
        with self._tx(write=True) as conn:
            current = conn.execute(select(cells_table).where(c.sweep == row.sweep, c.cell_key == row.cell_key)
                                   ).mappings().first()
            if current is None or CellRow.from_mapping(current) != row:
                return False
            res = conn.execute(update(cells_table).where(c.sweep == row.sweep, c.cell_key == row.cell_key)
                               .values(**values))
            return res.rowcount == 1

    def delete(self, row: CellRow) -> bool:
        """Remove a damaged row no cell of the plan can rebuild (``status --repair``); False when it changed."""
        c = cells_table.c
        with self._tx(write=True) as conn:
            current = conn.execute(select(cells_table).where(c.sweep == row.sweep, c.cell_key == row.cell_key)
                                   ).mappings().first()
            if current is None or CellRow.from_mapping(current) != row:
                return False
            conn.execute(cells_table.delete().where(c.sweep == row.sweep, c.cell_key == row.cell_key))
            return True

    def record_finished(self, row: CellRow, run_id: str, duration_s: float | None, worker: str) -> bool:
        """Record an unclaimed row (pending or failed, as read) FINISHED by ``run_id``, a FINISHED MLflow run of the
        cell (``record.rebuild``); False when the row changed since it was read (a worker claimed it)."""
        c = cells_table.c
        with self._tx(write=True) as conn:
            res = conn.execute(
                update(cells_table)
                .where(c.sweep == row.sweep, c.cell_key == row.cell_key, c.version == row.version,
                       c.state.in_([PENDING, FAILED]))
                .values(state=FINISHED, run_id=run_id, duration_s=duration_s, worker=worker, token=None,
                        heartbeat=None, finished_at=self._now, failure_reason=None, version=c.version + 1))
            return res.rowcount == 1

    # -- claims ------------------------------------------------------------------
    def _claimable(self, max_retries: int, stale_after_s: float, overdue: Mapping[str, float] | None = None):
        """The claim rule. ``overdue``: cell key -> a heartbeat from the future (ahead of the database's clock)
        that the claimer saw unchanged for ``stale_after_s`` of its own clock (``liveness.FutureHeartbeats``):
        stale too, as long as it still is that value."""
        c = cells_table.c
        return or_(
            c.state == PENDING,
            and_(c.state == FAILED, c.attempts <= max_retries),
            and_(c.state == RUNNING, or_(c.heartbeat.is_(None), c.heartbeat < self._now - float(stale_after_s))),
            *(and_(c.cell_key == key, c.state == RUNNING, c.heartbeat == hb) for key, hb in (overdue or {}).items()),
        )

    def claim(self, sweep: str, keys: Sequence[str], worker: str, *, max_retries: int,
              stale_after_s: float, overdue: Mapping[str, float] | None = None) -> Claim | None:
        """Take one claimable cell of ``keys`` (pending first, then retries, then stale claims), or None.
        A damaged row (``CellRow.damage``) is never taken: the others are looked at instead."""
        c = cells_table.c
        claimable = self._claimable(max_retries, stale_after_s, overdue)
        order = [(c.state == FAILED).asc(), c.ord, c.cell_key]
        damaged: set[str] = set()
        for _ in range(2 * len(keys) + 1):
            with self._tx(write=True) as conn:
                q = select(cells_table).where(c.sweep == sweep, c.cell_key.in_([k for k in keys if k not in damaged]),
                                              claimable)
                q = q.order_by(*order).limit(1)
                if self.dialect == "postgresql":
                    q = q.with_for_update(skip_locked=True)
                m = conn.execute(q).mappings().first()
                if m is None:
                    return None
                row = CellRow.from_mapping(m)
                if row.damage is not None:
                    damaged.add(row.cell_key)
                    continue
                previous = row if row.state == RUNNING else None
                exhausted = previous is not None and row.attempts > max_retries
                token = uuid.uuid4().hex
                res = conn.execute(
                    update(cells_table)
                    .where(c.sweep == sweep, c.cell_key == row.cell_key, c.version == row.version, claimable)
                    .values(state=RUNNING, token=token, worker=worker, version=c.version + 1,
                            attempts=c.attempts + (0 if exhausted else 1), heartbeat=self._now,
                            claimed_at=self._now, finished_at=None, duration_s=None,
                            # a takeover keeps the lost worker's run: resumable from its checkpoint, still the
                            # cell's until this claim names its own run (set_run_id), so nothing deletes it meanwhile
                            run_id=row.run_id if previous is not None else None,
                            failure_reason=row.failure_reason if exhausted else None)
                )
                if res.rowcount == 1:
                    won = CellRow(**{**row.__dict__, "state": RUNNING, "token": token, "worker": worker,
                                     "attempts": row.attempts + (0 if exhausted else 1), "version": row.version + 1})
                    released = row.run_id if row.state in (PENDING, FAILED) or previous is not None else None
                    return Claim(won, token, previous, exhausted, released)
            # lost the race for that row (optimistic path): look again
        return None

    def _by_token(self, conn: Connection, claim: str, /, **values: Any) -> bool:
        c = cells_table.c
        res = conn.execute(update(cells_table).where(c.token == claim, c.state == RUNNING).values(**values))
        return res.rowcount == 1

    def heartbeat(self, token: str) -> bool:
        """Refresh the claim; False when it is no longer ours (reclaimed or reset)."""
        with self._tx(write=True) as conn:
            return self._by_token(conn, token, heartbeat=self._now)

    def set_run_id(self, token: str, run_id: str) -> bool:
        with self._tx(write=True) as conn:
            return self._by_token(conn, token, run_id=run_id, heartbeat=self._now)

    def finish(self, token: str, run_id: str, duration_s: float) -> bool:
        c = cells_table.c
        with self._tx(write=True) as conn:
            return self._by_token(conn, token, state=FINISHED, run_id=run_id, duration_s=duration_s,
                                  finished_at=self._now, failure_reason=None, version=c.version + 1)

    def fail(self, token: str, reason: str, run_id: str | None = None, duration_s: float | None = None,
             spent: bool = True) -> bool:
        """FAILED with ``reason``; ``spent=False`` (a failure of the machine, e.g. a full disk): the attempt is not
        counted, so the next sweep retries (resumes) the cell even when this was its last attempt."""
        c = cells_table.c
        with self._tx(write=True) as conn:
            return self._by_token(conn, token, state=FAILED, run_id=run_id, duration_s=duration_s,
                                  finished_at=self._now, failure_reason=reason[:4000], version=c.version + 1,
                                  **({} if spent else {"attempts": c.attempts - 1}))

    def release(self, token: str, reason: str | None = None) -> bool:
        """Give the cell back (Ctrl-C, a busy database): pending again, the attempt not counted, ``reason`` kept."""
        c = cells_table.c
        with self._tx(write=True) as conn:
            return self._by_token(conn, token, state=PENDING, token=None, worker=None, heartbeat=None,
                                  attempts=c.attempts - 1, version=c.version + 1,
                                  failure_reason=reason[:4000] if reason else None)

    # -- staged sweeps -------------------------------------------------------------
    def record_selection(self, sweep: str, plan_key: str, stage: str, selection: dict[str, Any]) -> bool:
        """Store a stage's selection unless one is there already; True when this call wrote it."""
        try:
            with self._tx(write=True) as conn:
                conn.execute(selections_table.insert().values(sweep=sweep, plan_key=plan_key, stage=stage,
                                                              selection=json.dumps(selection), created_at=self._now))
            return True
        except IntegrityError:  # another process recorded it first: theirs is the selection
            return False

    def selection(self, sweep: str, plan_key: str, stage: str) -> dict[str, Any] | None:
        if not self.exists():
            return None
        with self.engine.connect() as conn:
            if not inspect(conn).has_table(SELECTIONS):
                return None
        c = selections_table.c
        q = select(c.selection).where(c.sweep == sweep, c.plan_key == plan_key, c.stage == stage)
        with self._tx() as conn:
            text = conn.execute(q).scalar_one_or_none()
        return None if text is None else json.loads(text)

    def running(self, sweep: str, stale_after_s: float) -> list[CellRow]:
        """The cells of ``sweep`` a live worker runs now (RUNNING, heartbeat within ``stale_after_s``); none when
        the table does not exist (a report of runs made without a sweep)."""
        if not self.exists():
            return []
        c = cells_table.c
        q = select(cells_table).where(c.sweep == sweep, c.state == RUNNING,
                                      c.heartbeat >= self._now - float(stale_after_s)).order_by(c.ord)
        with self._tx() as conn:
            return [CellRow.from_mapping(m) for m in conn.execute(q).mappings()]

    def all_done(self, sweep: str, keys: Sequence[str], max_retries: int) -> bool:
        """True when every cell is finished or failed with no retry left (nothing left to run or wait for)."""
        c = cells_table.c
        q = select(cells_table.c.cell_key).where(
            c.sweep == sweep, c.cell_key.in_(list(keys)),
            or_(c.state.in_([PENDING, RUNNING]), and_(c.state == FAILED, c.attempts <= max_retries)),
        ).limit(1)
        with self._tx() as conn:
            return conn.execute(q).first() is None


class StorageError(BronchoError):
    """The sweep storage could not be reached or queried (URL shown with its password hidden)."""


def _now_sql(dialect: str) -> str:
    """The database server's clock in epoch seconds (shared by every machine using the database)."""
    if dialect == "sqlite":
        return "((julianday('now') - 2440587.5) * 86400.0)"
    if dialect == "postgresql":
        return "CAST(EXTRACT(EPOCH FROM clock_timestamp()) AS DOUBLE PRECISION)"
    if dialect in ("mysql", "mariadb"):
        return "UNIX_TIMESTAMP(NOW(6))"
    raise BronchoError(f"storage.url: database {dialect!r} is not supported for sweeps (use sqlite or postgresql)")


def _make_engine(url: str, timeout_s: float, busy_timeout_s: float = SQLITE_BUSY_MS / 1000) -> Engine:
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"timeout": busy_timeout_s})
        _sqlite_events(engine, max(1, int(busy_timeout_s * 1000)))
        return engine
    args = {"connect_timeout": max(2, math.ceil(timeout_s))} if urls.is_postgres(url) else {}
    return create_engine(url, pool_pre_ping=True, connect_args=args)


def _sqlite_events(engine: Engine, busy_ms: int = SQLITE_BUSY_MS) -> None:
    @event.listens_for(engine, "connect")
    def _connect(dbapi_conn, _record) -> None:
        dbapi_conn.isolation_level = None  # we issue BEGIN ourselves (pysqlite's own is deferred)
        cur = dbapi_conn.cursor()
        cur.execute(f"PRAGMA busy_timeout = {busy_ms}")
        cur.execute("PRAGMA journal_mode = WAL")  # readers (status, monitors) never block the writer
        cur.execute("PRAGMA synchronous = NORMAL")
        cur.close()

    @event.listens_for(engine, "begin")
    def _begin(conn: Connection) -> None:
        # A write transaction takes the write lock up front, so a read-then-update
        # never fails half-way with SQLITE_BUSY_SNAPSHOT; readers use deferred BEGIN.
        conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("sweep_write") else "BEGIN")
