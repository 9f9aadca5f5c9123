"""The MLflow client of a config's store: set up once, reachable within ``runs.timeout_s``, patient when busy.

``client_for(cfg)`` opens the store (creating MLflow's tables once, serialised across processes and
machines), relocates a copied project's artifacts, and returns a client every call of which is retried
through a busy or briefly unavailable database for at most ``runs.busy_timeout_s`` (``retry.retry``).
"""

from __future__ import annotations

import functools
import logging
import math
import os
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")  # before mlflow is imported
os.environ.setdefault("DO_NOT_TRACK", "true")
os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")  # no "View run ... at" line per run end

from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from sqlalchemy import create_engine, text
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.pool import NullPool

from .. import extras, urls
from ..config import Config
from ..errors import BronchoError, MlflowBusy, MlflowUnreachable, WriteFailed  # resumable kinds: defined there
from ..io import file_lock
from ..retry import disk_full, disk_full_line, is_transient_store, retry, with_races
from .records import EXPERIMENT_TAGS, log_metrics
from .relocation import relocate_artifacts
from .sqlite_busy import set_busy_timeout

# pg_advisory_lock key under which MLflow's first-time table creation runs (any fixed 64-bit number will do;
# every bronchopose process on every machine must use the same one).
MIGRATION_LOCK_KEY = 0x62726F6E63686F  # "broncho"
log = logging.getLogger(__name__)
HTTP_RETRIES = 2  # MLflow's HTTP client: retries of a failed request (each waits up to runs.timeout_s)
_probed: set[str] = set()  # MLflow servers found answering by this process


def transient(exc: BaseException) -> bool:
    """An MLflow store briefly away (locked or restarting database, server answering 5xx or not at all): worth
    waiting for. A BronchoError (e.g. unreachable at the start: runs.timeout_s rules) is final."""
    return not isinstance(exc, BronchoError) and is_transient_store(exc)


def retry_busy(fn: Callable[[], Any], what: str, bound_s: float, shown: str) -> Any:
    """``fn()``, retried while the MLflow store (its database or its server) is busy or briefly away, for at most
    ``bound_s`` (``runs.busy_timeout_s``, the same bound as a SQLite lock); then MlflowBusy (resumable). A write
    that lost a unique-key race (two runs logging the same dataset input at once: the row exists now) is tried
    again too, a few times (``retry.with_races``): the platform's race, never the cell's failure."""
    def give_up(exc: BaseException) -> BaseException:
        return MlflowBusy(f"runs.uri {shown}: the MLflow store stayed busy or unavailable for {bound_s:g} s "
                          f"({urls.error_line(exc)}, during {what}); try again when it is back, or raise "
                          "runs.busy_timeout_s")

    try:
        return retry(fn, transient=with_races(transient), what=f"MLflow store busy ({what})", bound_s=bound_s,
                     give_up=give_up)
    except Exception as exc:
        if isinstance(exc, BronchoError) or (full := disk_full(exc)) is None:
            raise
        raise store_full(shown, what, *full) from None


def store_full(shown: str, what: str, why: str, file: str | None) -> WriteFailed:
    """A write of the MLflow store refused by a full disk, in one line (MLflow and SQLAlchemy raise it with the
    SQL statement and its parameters on several lines): the folder, the space free there, what was written."""
    where = file or urls.sqlite_file(shown)
    place = disk_full_line(where, why) if where is not None else f"the MLflow server's disk is full ({why})"
    return WriteFailed(f"runs.uri {shown}: {place}, during {what}; free space there and run the same command "
                       "again (an unfinished run resumes from its checkpoint)")


class BusyRetryClient:
    """An ``MlflowClient`` whose every call is retried through a busy database (``retry_busy``)."""

    def __init__(self, client: MlflowClient, bound_s: float, shown: str) -> None:
        self.raw, self._bound, self._shown = client, bound_s, shown

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self.raw, name)
        if not callable(attr):
            return attr

        @functools.wraps(attr)
        def call(*args: Any, **kw: Any) -> Any:
            return retry_busy(lambda: attr(*args, **kw), name, self._bound, self._shown)

        return call


class MetricBuffer:
    """A run's metrics (per validation) kept in memory while the MLflow store is away, sent in order when it
    answers again: an outage during training is not fatal. ``flush(wait=True)`` (the run's end) waits for the
    store within runs.busy_timeout_s like any call, then raises MlflowBusy; a resumed run re-sends what its
    checkpoint's history holds and MLflow lacks (``training.run``)."""

    def __init__(self, client: Any, run_id: str) -> None:
        self.client, self.run_id = client, run_id
        self.pending: list[tuple[int, dict[str, float]]] = []
        self._warned = False

    def log(self, values: dict[str, float], step: int) -> None:
        self.pending.append((step, dict(values)))
        self.flush()

    def log_points(self, points: list[tuple[int, dict[str, float]]]) -> None:
        """Several steps' metrics at once (the training-curve points of a validation window, ``Trainer.on_curves``)."""
        self.pending.extend((step, dict(values)) for step, values in points)
        self.flush()

    def flush(self, wait: bool = False) -> bool:
        """Send what is pending; False (logged once per outage) when the store is away and ``wait`` is False."""
        sender = self.client if wait else getattr(self.client, "raw", self.client)  # raw: no busy wait
        while self.pending:
            step, values = self.pending[0]
            try:
                log_metrics(sender, self.run_id, values, step=step)
            except Exception as exc:  # noqa: BLE001 - kept for later when the store is briefly away
                if wait or not transient(exc):
                    raise
                if not self._warned:
                    log.warning("MLflow store unavailable (%s): metrics of step %d and later are kept in memory "
                                "and sent when it answers", urls.error_line(exc, 300), step)
                self._warned = True
                return False
            self.pending.pop(0)
        if self._warned:
            log.info("MLflow store answers again: buffered metrics of run %s sent", self.run_id)
        self._warned = False
        return True


def _quiet() -> None:
    for name in ("mlflow", "alembic"):
        logging.getLogger(name).setLevel(logging.WARNING)
    # urllib3 warns at each of MLflow's HTTP retries ("Retrying (Retry(total=1 ...)) after connection broken");
    # an outage is reported once, by the retry loop, in one line
    logging.getLogger("urllib3").setLevel(logging.ERROR)
    # MLflow logs every database error with its traceback before raising it; we report it in one line.
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)


def redacted_uri(cfg: Config) -> str:
    """The MLflow URI as it may be printed (password hidden)."""
    return urls.redact(cfg.paths.mlflow_uri)


def client_for(cfg: Config, *, reading: bool = False) -> MlflowClient:
    """An MLflow client on the config's store, its tables created; a dead server fails within runs.timeout_s.

    ``reading`` (report, status): an experiment whose artifacts live outside ``runs.artifacts`` is read
    where they are instead of refused (``relocate_artifacts``); a run is never written there.

    MLflow creates (migrates) its tables when it first opens a store, and two
    processes doing that at once collide: on SQLite a file lock, on PostgreSQL
    a database advisory lock (machines share nothing else) serialise it. Every
    call of the returned client is retried while the database is busy, for at
    most ``runs.busy_timeout_s`` (then ``MlflowBusy``, one line).
    """
    _quiet()  # mlflow configures its own loggers when it is first used
    uri, timeout_s, bound = cfg.paths.mlflow_uri, cfg.runs.timeout_s, cfg.runs.busy_timeout_s
    shown = urls.redact(uri)
    set_http_limits(timeout_s)
    db = urls.sqlite_file(uri)
    if db is not None:
        urls.check_sqlite(db, "runs.uri")  # a damaged file: one line naming it and what to do
        set_busy_timeout(db, bound)
        with file_lock(f"{db}.lock"):
            def opened_sqlite() -> MlflowClient:
                c = _open(uri)
                relocate_artifacts(c, cfg, rewrite=True, reading=reading)
                return c

            client = retry_busy(opened_sqlite, "opening the store", bound, shown)
    elif urls.is_server(uri):
        probe_server(uri, timeout_s)
        client = _client(uri)
    elif urls.is_postgres(uri):
        def opened() -> MlflowClient:
            with database_lock(uri, timeout_s, what="runs.uri"):  # also the reachability check
                c = _open(uri)
            relocate_artifacts(c, cfg, rewrite=False, reading=reading)
            return c

        client = retry_busy(opened, "opening the store", bound, shown)
    else:
        client = _client(uri)
    return BusyRetryClient(client, bound, shown)


def store_missing(cfg: Config) -> bool:
    """True when ``runs.uri`` is a SQLite file that does not exist (opening it would create an empty store)."""
    db = urls.sqlite_file(cfg.paths.mlflow_uri)
    return db is not None and not db.is_file()


def require_store(cfg: Config) -> None:
    """Commands that only read runs (report, track, the API's model loading) refuse a missing SQLite store in one
    line instead of creating an empty one (a mistyped ``runs.uri`` path leaves no file behind)."""
    if store_missing(cfg):
        raise BronchoError(f"runs.uri {redacted_uri(cfg)}: no MLflow store there yet; check the path, or run "
                           "`bronchopose sweep` or `bronchopose train` first")


def check_reachable(cfg: Config) -> None:
    """Fail within runs.timeout_s (one line) when the config's MLflow server or database does not answer."""
    uri, timeout_s = cfg.paths.mlflow_uri, cfg.runs.timeout_s
    if urls.is_server(uri):
        probe_server(uri, timeout_s)
    elif urls.is_postgres(uri):
        with database_lock(uri, timeout_s, what="runs.uri"):
            pass


def _client(uri: str) -> MlflowClient:
    try:
        return MlflowClient(tracking_uri=uri)
    except MlflowException as exc:
        raise BronchoError(f"runs.uri {urls.redact(uri)}: {urls.error_line(exc)}") from None


def _open(uri: str) -> MlflowClient:
    """A client whose store exists: the first request creates MLflow's tables."""
    client = _client(uri)
    client.search_experiments(max_results=1)
    return client


def set_http_limits(timeout_s: float) -> None:
    """MLflow's HTTP client reads these at each request: a dead server costs seconds, not minutes of retries."""
    os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] = str(max(1, math.ceil(timeout_s)))
    os.environ["MLFLOW_HTTP_REQUEST_MAX_RETRIES"] = str(HTTP_RETRIES)
    os.environ["MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR"] = "1"


def probe_server(uri: str, timeout_s: float) -> None:
    """One request to an ``http(s)://`` MLflow server; MlflowUnreachable (one line) if it does not answer."""
    if uri in _probed or not uri.startswith(("http://", "https://")):
        return
    parts = urllib.parse.urlsplit(uri)
    netloc = parts.netloc.rpartition("@")[2]  # credentials go through MLflow's own settings, not the probe
    url = urllib.parse.urlunsplit((parts.scheme, netloc, parts.path.rstrip("/") + "/health", "", ""))
    try:
        urllib.request.urlopen(url, timeout=timeout_s).close()
    except urllib.error.HTTPError:
        pass  # it answered (an error status still means a live server)
    except (OSError, ValueError) as exc:
        reason = getattr(exc, "reason", None) or exc or type(exc).__name__
        raise MlflowUnreachable(
            f"runs.uri {urls.redact(uri)}: no answer within {timeout_s:g} s ({reason}); check that the MLflow "
            "server is running and reachable from this machine (the limit is runs.timeout_s)") from None
    _probed.add(uri)


def connect_timeout(timeout_s: float) -> int:
    """libpq's ``connect_timeout`` for runs.timeout_s: whole seconds, at least 2 (libpq's own minimum)."""
    return max(2, math.ceil(timeout_s))


@contextmanager
def database_lock(url: str, timeout_s: float, what: str = "database", key: int = MIGRATION_LOCK_KEY
                  ) -> Iterator[None]:
    """Hold a PostgreSQL session advisory lock on ``key`` for the block, on a short-lived connection of its own.

    Serialises first-time schema creation across machines. Connecting gives up
    after ``timeout_s`` with one line naming the (redacted) URL: the
    reachability check of a database before a library with long retries opens it.
    """
    shown, limit = urls.redact(url), connect_timeout(timeout_s)
    extras.require("postgres", f"{what} {shown}")
    try:
        engine = create_engine(urls.sqlalchemy(url), poolclass=NullPool, connect_args={"connect_timeout": limit})
        conn = engine.connect()
    except (SQLAlchemyError, ImportError, ValueError) as exc:
        raise MlflowUnreachable(
            f"{what} {shown}: cannot connect within {limit} s ({urls.error_line(exc)}); check the "
            "host, port, database name and credentials, and that the server is running") from None
    try:
        conn.execute(text("SELECT pg_advisory_lock(:key)"), {"key": key})
        yield
    finally:  # closing the session releases the lock too (also when the block failed)
        conn.close()
        engine.dispose()


class ExperimentDeleted(BronchoError):
    """The experiment was deleted by hand (the MLflow UI): nothing is written to it, nothing read from it."""


def deleted_line(name: str, exp_id: str, where: str) -> str:
    """The one line every command gives for a deleted experiment: what it is, and the two ways on."""
    return (f"MLflow experiment {name!r} (id {exp_id}) in {where} was deleted (in the MLflow UI): restore it there "
            f"(the experiments list, 'deleted'; or `mlflow experiments restore --experiment-id {exp_id}`), or give "
            f"the config a new `name` (or runs.experiment) to start a new experiment")


def find_experiment(client: MlflowClient, name: str, where: str = "the MLflow store") -> Any:
    """The experiment ``name`` (None: there is none); ``ExperimentDeleted`` when it was deleted by hand (MLflow
    still finds it by name, refuses to write to it and hides its runs)."""
    exp = client.get_experiment_by_name(name)
    if exp is not None and getattr(exp, "lifecycle_stage", "active") == "deleted":
        raise ExperimentDeleted(deleted_line(name, exp.experiment_id, where))
    return exp


def experiment_id(client: MlflowClient, cfg: Config, name: str | None = None) -> str:
    """Get or create the config's experiment; concurrent creators agree on one id (``ExperimentDeleted``: one that
    was deleted by hand is neither used nor made again)."""
    name = name or cfg.experiment_name
    exp = find_experiment(client, name, redacted_uri(cfg))
    if exp is not None:
        return exp.experiment_id
    location = cfg.paths.artifacts.as_uri() if urls.is_direct_store(cfg.paths.mlflow_uri) else None

    def create() -> str:
        try:
            return client.create_experiment(name, artifact_location=location, tags=EXPERIMENT_TAGS)
        except (MlflowException, SQLAlchemyError):  # another worker created it first (or is committing it)
            exp = client.get_experiment_by_name(name)
            if exp is not None:
                return exp.experiment_id
            raise

    return retry(create, transient=lambda e: isinstance(e, (MlflowException, SQLAlchemyError)), attempts=3,
                 what=f"creating MLflow experiment {name!r}", first_delay_s=0.2, quiet=True)


def mark_training_experiment(client: MlflowClient, exp_id: str) -> None:
    """Tag an experiment made before EXPERIMENT_TAGS existed, so MLflow 3's UI opens it on its runs table."""
    exp = client.get_experiment(exp_id)
    for key, value in EXPERIMENT_TAGS.items():
        if key not in exp.tags:
            client.set_experiment_tag(exp_id, key, value)
