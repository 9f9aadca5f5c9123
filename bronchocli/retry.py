"""The one retry loop: call again with exponential backoff while a failure is transient, within a bound.

Every place that waits out something briefly unavailable (a locked SQLite file, a restarting PostgreSQL,
an MLflow server answering 5xx, a slurmctld that refuses a request) goes through :func:`retry`, so the
backoff, the bound and the log line are written once. The caller says what counts as transient and what
to raise when the bound is spent.

``is_transient_db`` is the shared judgement for databases (the claims table and MLflow's store alike);
``is_transient_store`` adds an MLflow server's answers (5xx, dropped connections); ``is_write_race`` is a
write that lost a race to an equal one (a unique key taken a moment earlier), worth a few more tries only
(``with_races``). ``disk_full`` is the one recogniser of a full (or failing) disk under a write: never
transient, never worth an attempt of a cell (the callers turn it into one line naming the folder).
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from . import pathcheck, urls
from .io import fmt_bytes

T = TypeVar("T")
log = logging.getLogger(__name__)

# Error texts of a database that is busy or briefly away (SQLite locks; PostgreSQL restarts, failovers,
# dropped connections, serialisation failures): worth retrying. Anything else fails at once.
TRANSIENT_DB = ("database is locked", "database table is locked", "database schema is locked", "could not connect",
                "connection refused", "server closed the connection", "terminating connection",
                "the database system is", "could not serialize access", "deadlock detected", "connection timed out",
                "connection reset", "ssl syscall error", "timeout expired", "connection is closed",
                "too many connections", "remaining connection slots")


# Error texts of an MLflow server that is briefly away or whose own database is (MLflow's HTTP client retries
# 429/5xx answers and connection errors itself, then raises "API request to ... failed with exception ...
# Max retries exceeded ... too many 503 error responses"): worth retrying too, within the same bound.
TRANSIENT_HTTP = ("max retries exceeded", "error responses", "failed with timeout exception", "read timed out",
                  "connection aborted", "remotedisconnected", "temporarily_unavailable", "service unavailable",
                  "bad gateway", "gateway timeout",
                  # MLflow's own line for a 5xx answer its HTTP client did not retry (its cached session's retry
                  # policy is per process: "... failed with error code 503 != 200")
                  "failed with error code 500", "failed with error code 502", "failed with error code 503",
                  "failed with error code 504")


# Error texts of a write that lost a race to an equal write (MLflow's store reads, then inserts: two runs
# logging the same dataset input at once both find no row and both insert it, on PostgreSQL behind an MLflow
# server "BAD_REQUEST: (psycopg2.errors.UniqueViolation) duplicate key value violates unique constraint
# "dataset_pk""; SQLite "UNIQUE constraint failed"; MySQL "Duplicate entry"). The row exists now, so the same
# call again succeeds: an infrastructure hiccup, never the run's failure. A conflict that outlasts
# RACE_RETRIES tries is a real one and is raised.
WRITE_RACE = ("uniqueviolation", "duplicate key value violates unique constraint", "unique constraint failed",
              "duplicate entry")
RACE_RETRIES = 3


def _chain_has(exc: BaseException, texts: tuple[str, ...]) -> bool:
    seen, e = 0, exc
    while e is not None and seen < 6:
        text = f"{e} {getattr(e, 'orig', '') or ''}".lower()
        if any(t in text for t in texts):
            return True
        e, seen = e.__cause__ or e.__context__, seen + 1
    return False


def is_transient_db(exc: BaseException) -> bool:
    """True for a busy or briefly unavailable database (the error, or one it was raised from)."""
    return _chain_has(exc, TRANSIENT_DB)


def is_transient_store(exc: BaseException) -> bool:
    """True for an MLflow store briefly away: its database (as ``is_transient_db``) or its server (HTTP 5xx,
    connection errors, timeouts: ``TRANSIENT_HTTP``)."""
    return _chain_has(exc, TRANSIENT_DB + TRANSIENT_HTTP)


# A write the disk refused: full, over quota, read-only or failing (an OSError's errno; SQLite's and the
# drivers' texts, also when SQLAlchemy or MLflow wrapped them). Not transient: it lasts until space is freed.
DISK_ERRNOS = (errno.ENOSPC, errno.EIO, errno.EDQUOT, errno.EROFS)
DISK_TEXTS = ("database or disk is full", "disk i/o error", "no space left on device", "read-only file system",
              "disk quota exceeded")


def disk_full(exc: BaseException) -> tuple[str, str | None] | None:
    """``(why, file)`` when ``exc`` (or one it was raised from) is a write the disk refused (``file``: the path
    written, else None); None for anything else. A copy (``shutil.copyfile``'s sendfile, MLflow's artifact
    upload) names its source first and the file it was writing second: the second is the one on the full disk."""
    seen, e = 0, exc
    while e is not None and seen < 8:
        if isinstance(e, OSError) and e.errno in DISK_ERRNOS:
            written = getattr(e, "filename2", None) or e.filename
            return os.strerror(e.errno), (str(written) if written else None)
        text = f"{e} {getattr(e, 'orig', '') or ''}".lower()
        found = next((t for t in DISK_TEXTS if t in text), None)
        if found:
            return found, None
        e, seen = e.__cause__ or e.__context__, seen + 1
    return None


def disk_full_line(where: str | os.PathLike, why: str, need: int | None = None) -> str:
    """One line for a full disk: the file or folder written (``where``), why, the file system that is full (its
    mount point) and the space free on it and, when known, the space needed (``need`` bytes)."""
    folder = pathcheck.nearest_existing(where)
    folder = folder if folder.is_dir() else folder.parent  # a file that exists: the space of its folder
    try:
        free = f"{fmt_bytes(shutil.disk_usage(folder).free)} free on the file system mounted at {pathcheck.mount_point(folder)}"
    except OSError:
        free = "free space unknown"
    needs = f"; needs about {fmt_bytes(need)} free there" if need else ""
    return f"{where}: disk full ({why}; {free}){needs}"


def is_write_race(exc: BaseException) -> bool:
    """True for a unique-key conflict (the error, or one it was raised from): an equal write got there first."""
    return _chain_has(exc, WRITE_RACE)


def with_races(transient: Callable[[BaseException], bool], races: int = RACE_RETRIES
               ) -> Callable[[BaseException], bool]:
    """``transient``, and also a write race (``is_write_race``) for its first ``races`` occurrences: a predicate
    for one :func:`retry` call (it counts), so a lost race is tried again but a lasting conflict is raised."""
    seen = [0]

    def judge(exc: BaseException) -> bool:
        if transient(exc):
            return True
        if is_write_race(exc) and seen[0] < races:
            seen[0] += 1
            return True
        return False

    return judge


def planned_attempts(bound_s: float | None, attempts: int | None, first_delay_s: float, max_delay_s: float) -> int:
    """The most calls :func:`retry` makes: ``attempts``, or as many as its pauses allow within ``bound_s`` (each
    call takes time too, so fewer may be made), whichever is smaller."""
    most = attempts if attempts is not None else 10**9
    if bound_s is None:
        return most
    calls, waited, delay = 1, 0.0, first_delay_s
    while waited < bound_s and calls < most:
        waited, calls, delay = waited + delay, calls + 1, min(2 * delay, max_delay_s)
    return calls


def retry(fn: Callable[[], T], *, transient: Callable[[BaseException], bool], what: str,
          bound_s: float | None = None, attempts: int | None = None,
          give_up: Callable[[BaseException], BaseException | None] | None = None,
          first_delay_s: float = 0.05, max_delay_s: float = 2.0, quiet: bool = False) -> T:
    """``fn()``, called again after a growing pause while it fails with a ``transient`` error.

    Stops after ``bound_s`` seconds or ``attempts`` calls (whichever is given; both: the first reached).
    Then ``give_up(last error)`` is raised if it returns an exception, else the last error itself.
    A non-transient error is raised at once. An outage is announced once (unless ``quiet``): one warning naming
    ``what``, the error and the attempt (``retrying (attempt 2/N)``, N the most it makes), again only when the
    error changes; the later attempts are logged at debug level, and a call that succeeds after a warning says so.
    """
    if bound_s is None and attempts is None:
        raise ValueError("retry needs bound_s or attempts")
    deadline = None if bound_s is None else time.monotonic() + bound_s
    most = planned_attempts(bound_s, attempts, first_delay_s, max_delay_s)
    delay, calls, announced = first_delay_s, 0, None
    while True:
        calls += 1
        try:
            result = fn()
        except Exception as exc:  # noqa: BLE001 - re-raised unless transient and within the bound
            if not transient(exc):
                raise
            left = None if deadline is None else deadline - time.monotonic()
            if (left is not None and left <= 0) or (attempts is not None and calls >= attempts):
                replacement = give_up(exc) if give_up is not None else None
                if replacement is None:
                    raise
                raise replacement from None
            line = urls.error_line(exc)  # a URL may hold a password
            bound = f" within {bound_s:g} s" if bound_s is not None else ""
            if not quiet and line != announced:
                log.warning("%s: %s; retrying (attempt %d/%d%s)...", what, line, calls + 1, max(most, calls + 1),
                            bound)
                announced = line
            else:
                log.debug("%s: %s; retrying (attempt %d/%d%s)", what, line, calls + 1, max(most, calls + 1), bound)
            time.sleep(delay if left is None else min(delay, left))
            delay = min(2 * delay, max_delay_s)
            continue
        if announced is not None:
            log.info("%s: succeeded at attempt %d", what, calls)
        return result
