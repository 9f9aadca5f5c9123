"""MLflow conventions: store set-up, experiment, run tags and params, metric names, run lookup.

One MLflow run per grid cell. Runs are found again by their tags (``cell_key``,
``sweep``, ...), never by name. Everything goes through an explicit
``MlflowClient`` (no fluent global state), so one process can drive many runs.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import platform
import socket
import sqlite3
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Mapping

os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")  # before mlflow is imported
os.environ.setdefault("DO_NOT_TRACK", "true")

from mlflow.entities import Metric, Param, Run
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy import inspect as sqlalchemy_inspect
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.pool import NullPool, Pool

from . import __version__, extras, urls
from .cells import FIELDS, Cell
from .config import Config
from .errors import BronchoError, TrackingBusy  # TrackingBusy: a resumable kind, defined with the others
from .io import file_lock

# Tags every cell run carries (report/status/sweep filter on them): the cell's coordinates, and these.
CELL_TAGS = FIELDS
TAG_CELL_KEY = "cell_key"
TAG_SWEEP = "sweep"
TAG_FINGERPRINT = "dataset_fingerprint"
TAG_GIT = "git_commit"
TAG_VERSION = "bronchocli_version"
TAG_FAILURE = "failure_reason"
TAG_HPARAMS = "hparams_source"  # where hyperparameters came from ("config" or "optuna:<study>#<trial>")
TAG_KIND = "run_kind"  # "cell" (train/sweep), "trial" (tune), "sweep"/"study" (parents), "selection"
# MLflow's own fields (the UI shows them: source, commit, description, nesting)
TAG_NOTE = "mlflow.note.content"
TAG_PARENT = "mlflow.parentRunId"
TAG_SOURCE_NAME = "mlflow.source.name"
TAG_SOURCE_TYPE = "mlflow.source.type"
TAG_SOURCE_GIT = "mlflow.source.git.commit"
TAG_SOURCE_BRANCH = "mlflow.source.git.branch"
# MLflow 3's UI opens an experiment of this kind on its runs table, not on the GenAI overview.
EXPERIMENT_TAGS = {"mlflow.experimentKind": "custom_model_development"}
TAG_INIT = "init"  # backbone initialisation: "random", "imagenet:<torchvision file>", "file:<name>#<sha256>"

_PARAM_BATCH = 100  # MLflow's limit of params per log_batch call
# pg_advisory_lock key under which MLflow's first-time table creation runs (any fixed 64-bit number will do;
# every bronchopose process on every machine must use the same one).
MIGRATION_LOCK_KEY = 0x62726F6E63686F  # "broncho"
HTTP_RETRIES = 2  # MLflow's HTTP client: retries of a failed request (each waits up to tracking.timeout_s)
_probed: set[str] = set()  # tracking servers found answering by this process


class TrackingUnreachable(BronchoError):
    """The tracking server or database did not answer within ``tracking.timeout_s``."""


# -- busy databases: bounded retry with backoff ------------------------------------------------------------------

# Error texts of a database that is busy or briefly away (SQLite locks; PostgreSQL restarts, failovers,
# dropped connections, serialisation failures): worth retrying. Anything else fails at once.
TRANSIENT = ("database is locked", "database table is locked", "database schema is locked", "could not connect",
             "connection refused", "server closed the connection", "terminating connection",
             "the database system is", "could not serialize access", "deadlock detected", "connection timed out",
             "connection reset", "ssl syscall error", "timeout expired", "connection is closed",
             "too many connections", "remaining connection slots")
_sqlite_busy_ms: dict[str, int] = {}  # MLflow SQLite files of this process -> their busy timeout


def is_transient(exc: BaseException) -> bool:
    """True for a busy or briefly unavailable database (the error, or one it was raised from)."""
    seen, e = 0, exc
    while e is not None and seen < 6:
        text = f"{e} {getattr(e, 'orig', '') or ''}".lower()
        if any(t in text for t in TRANSIENT):
            return True
        e, seen = e.__cause__ or e.__context__, seen + 1
    return False


def retry_busy(fn: Callable[[], Any], what: str, bound_s: float, shown: str) -> Any:
    """``fn()``, retried with backoff while the database is busy, for at most ``bound_s``; then TrackingBusy."""
    deadline, delay = time.monotonic() + bound_s, 0.05
    while True:
        try:
            return fn()
        except Exception as exc:  # noqa: BLE001 - re-raised unless transient
            if isinstance(exc, BronchoError) or not is_transient(exc):  # e.g. unreachable: tracking.timeout_s rules
                raise
            left = deadline - time.monotonic()
            if left <= 0:
                raise TrackingBusy(
                    f"tracking.uri {shown}: the database stayed busy or unavailable for {bound_s:g} s "
                    f"({urls.redact(_first_line(exc))}, during {what}); another process holds it: try again, or raise "
                    "tracking.busy_timeout_s") from None
            logging.getLogger(__name__).warning("tracking database busy (%s), retrying", what)
            time.sleep(min(delay, left))
            delay = min(2 * delay, 2.0)


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


def _set_sqlite_busy(dbapi_conn: Any, _record: Any, *_proxy: Any) -> None:
    """Every new SQLite connection to one of this process's MLflow stores waits tracking.busy_timeout_s on a lock.

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
    """MLflow sets ``PRAGMA busy_timeout = 20000`` on every session: ours (tracking.busy_timeout_s) replaces it."""
    if _sqlite_busy_ms and statement.lstrip().upper().startswith("PRAGMA BUSY_TIMEOUT"):
        db = conn.engine.url.database
        ms = _sqlite_busy_ms.get(str(Path(db).resolve())) if db else None
        if ms:
            return f"PRAGMA busy_timeout = {int(ms)}", parameters
    return statement, parameters


event.listen(Pool, "connect", _set_sqlite_busy)
event.listen(Pool, "checkout", _set_sqlite_busy)  # pooled connections follow the bound of the current config
event.listen(Engine, "before_cursor_execute", _rewrite_busy_pragma, retval=True)


# -- zombies: runs left RUNNING by a process that died -----------------------------------------------------------

TAG_HOST, TAG_PID, TAG_PSTART = "process.host", "process.pid", "process.start"


def _process_start(pid: int) -> str | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def process_tags() -> dict[str, str]:
    """Which process runs a run (host, pid, start tick): lets the next process tell a live run from a dead one."""
    pid = os.getpid()
    return {TAG_HOST: socket.gethostname(), TAG_PID: str(pid), TAG_PSTART: _process_start(pid) or "?"}


def process_alive(tags: Mapping[str, str]) -> bool | None:
    """Whether the process a run's tags name is alive: True/False on this host, None when it cannot be told."""
    if tags.get(TAG_HOST) != socket.gethostname() or not str(tags.get(TAG_PID, "")).isdigit():
        return None
    pid = int(tags[TAG_PID])
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's live process
    start = _process_start(pid)
    want = tags.get(TAG_PSTART)
    return not (start is not None and want not in (None, "?") and start != want)  # pid reused by another process


def repair_zombie(client: Any, run: Run, who: str) -> bool:
    """End a RUNNING run whose process died (FAILED, with the reason); True when it did.

    A run still alive is refused (one line); one on another host is left alone (the sweep's heartbeat
    takeover settles those).
    """
    if run.info.status != "RUNNING":
        return False
    alive = process_alive(run.data.tags)
    if alive:
        raise BronchoError(f"run {run.info.run_id} is still running (process {run.data.tags.get(TAG_PID)} on this "
                           "host); stop it first (Ctrl-C or kill -TERM), then resume")
    if alive is None:
        return False
    reason = (f"process {run.data.tags.get(TAG_HOST)}:{run.data.tags.get(TAG_PID)} ended without closing the run "
              f"(killed, or the store was unwritable); marked FAILED by {who}")
    client.set_tag(run.info.run_id, TAG_FAILURE, reason)
    client.set_terminated(run.info.run_id, "FAILED")
    logging.getLogger(__name__).warning("run %s: %s", run.info.run_id, reason)
    return True


def _quiet() -> None:
    for name in ("mlflow", "alembic", "urllib3"):
        logging.getLogger(name).setLevel(logging.WARNING)
    # MLflow logs every database error with its traceback before raising it; we report it in one line.
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)


def redacted_uri(cfg: Config) -> str:
    """The tracking URI as it may be printed (password hidden)."""
    return urls.redact(cfg.paths.tracking_uri)


def client_for(cfg: Config, *, reading: bool = False) -> MlflowClient:
    """An MLflow client on the config's store, its tables created; a dead server fails within tracking.timeout_s.

    ``reading`` (report, status): an experiment whose artifacts live outside ``tracking.artifacts`` is read
    where they are instead of refused (``relocate_artifacts``); a run is never written there.

    MLflow creates (migrates) its tables when it first opens a store, and two
    processes doing that at once collide: on SQLite a file lock, on PostgreSQL
    a database advisory lock (machines share nothing else) serialise it. Every
    call of the returned client is retried while the database is busy, for at
    most ``tracking.busy_timeout_s`` (then ``TrackingBusy``, one line).
    """
    _quiet()  # mlflow configures its own loggers when it is first used
    uri, timeout_s, bound = cfg.paths.tracking_uri, cfg.tracking.timeout_s, cfg.tracking.busy_timeout_s
    shown = urls.redact(uri)
    set_http_limits(timeout_s)
    db = urls.sqlite_file(uri)
    if db is not None:
        _sqlite_busy_ms[str(Path(db).resolve())] = max(1, int(bound * 1000))
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
            with database_lock(uri, timeout_s, what="tracking.uri"):  # also the reachability check
                c = _open(uri)
            relocate_artifacts(c, cfg, rewrite=False, reading=reading)
            return c

        client = retry_busy(opened, "opening the store", bound, shown)
    else:
        client = _client(uri)
    return BusyRetryClient(client, bound, shown)


class ArtifactsElsewhere(BronchoError):
    """The experiment's artifacts are not where the config's ``tracking.artifacts`` says."""


def _local_path(location: str) -> Path | None:
    """The folder of a ``file:`` URI or a plain path; None for remote artifact stores (s3://, mlflow-artifacts:)."""
    if location.startswith("file:"):
        return Path(urllib.request.url2pathname(urllib.parse.urlparse(location).path))
    if location and "://" not in location and not location.startswith("mlflow-artifacts:"):
        return Path(location)
    return None


def relocate_artifacts(client: MlflowClient, cfg: Config, *, rewrite: bool, reading: bool = False) -> None:
    """Point the config's experiment (and its runs and models) at ``tracking.artifacts`` when it points elsewhere.

    MLflow stores absolute artifact locations, so a copied (``cp -a``) or moved
    project would otherwise write into, and report from, the original's folder,
    and a changed ``tracking.artifacts`` would be ignored. When the store is a
    project's own SQLite file (``rewrite``) and the runs' artifacts are under the
    configured folder (a copy or a move), or nowhere any more, or there are no
    runs, the locations are rewritten. Otherwise (a database shared with
    another folder, or artifacts that still live only in the old place) it
    refuses in one line naming both folders and the fix, before anything runs
    (``reading``: reports and status read the artifacts where they are instead).
    """
    uri = cfg.paths.tracking_uri
    if urls.is_server(uri) or not _is_local_store(uri):
        return  # a tracking server decides where artifacts go
    exp = client.get_experiment_by_name(cfg.experiment_name)
    have = _local_path(exp.artifact_location or "") if exp is not None else None
    want = cfg.paths.artifacts
    if have is None or have == want or have.resolve() == want.resolve():
        return
    runs = search_runs(client, [exp.experiment_id], max_results=50000)
    moved = any((want / r.info.run_id).exists() for r in runs)
    gone = not any((have / r.info.run_id).exists() for r in runs)
    if rewrite and (not runs or moved or gone):
        _rewrite_locations(uri, exp.experiment_id, exp.artifact_location, want.as_uri())
        return
    if reading:
        return
    fix = ("this copy shares the tracking database with the original: set tracking.experiment to a new name here, "
           f"or tracking.artifacts={have}" if not rewrite else
           f"move the folder there (mv {have} {want}), set tracking.artifacts={have}, or use a new tracking.experiment")
    raise ArtifactsElsewhere(f"MLflow experiment {cfg.experiment_name!r} keeps its artifacts in {have} but "
                             f"tracking.artifacts is {want}; {fix}")


def _rewrite_locations(uri: str, experiment: str, old: str, new: str) -> None:
    """Replace the ``old`` artifact-location prefix with ``new`` in one experiment's rows (one transaction)."""
    old, new = old.rstrip("/"), new.rstrip("/")
    statements = [
        ("experiments", "artifact_location", "experiment_id"),
        ("runs", "artifact_uri", "experiment_id"),
        ("logged_models", "artifact_location", "experiment_id"),
    ]
    engine = create_engine(urls.sqlalchemy(uri), poolclass=NullPool)
    try:
        with engine.begin() as conn:
            tables = set(sqlalchemy_inspect(conn).get_table_names())
            for table, column, key in statements:
                if table not in tables:
                    continue
                conn.execute(text(
                    f"UPDATE {table} SET {column} = :new || substr({column}, :n) "
                    f"WHERE {key} = :exp AND ({column} = :old OR substr({column}, 1, :m) = :prefix)"),
                    {"new": new, "n": len(old) + 1, "exp": int(experiment) if experiment.isdigit() else experiment,
                     "old": old, "m": len(old) + 1, "prefix": old + "/"})
    finally:
        engine.dispose()


def check_reachable(cfg: Config) -> None:
    """Fail within tracking.timeout_s (one line) when the config's tracking server or database does not answer."""
    uri, timeout_s = cfg.paths.tracking_uri, cfg.tracking.timeout_s
    if urls.is_server(uri):
        probe_server(uri, timeout_s)
    elif urls.is_postgres(uri):
        with database_lock(uri, timeout_s, what="tracking.uri"):
            pass


def _client(uri: str) -> MlflowClient:
    try:
        return MlflowClient(tracking_uri=uri)
    except MlflowException as exc:
        raise BronchoError(f"tracking.uri {urls.redact(uri)}: {urls.redact(_first_line(exc))}") from None


def _open(uri: str) -> MlflowClient:
    """A client whose store exists: the first request creates MLflow's tables."""
    client = _client(uri)
    client.search_experiments(max_results=1)
    return client


def _first_line(exc: BaseException) -> str:
    lines = str(getattr(exc, "orig", None) or exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def set_http_limits(timeout_s: float) -> None:
    """MLflow's HTTP client reads these at each request: a dead server costs seconds, not minutes of retries."""
    os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] = str(max(1, math.ceil(timeout_s)))
    os.environ["MLFLOW_HTTP_REQUEST_MAX_RETRIES"] = str(HTTP_RETRIES)
    os.environ["MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR"] = "1"


def probe_server(uri: str, timeout_s: float) -> None:
    """One request to an ``http(s)://`` tracking server; TrackingUnreachable (one line) if it does not answer."""
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
        raise TrackingUnreachable(
            f"tracking.uri {urls.redact(uri)}: no answer within {timeout_s:g} s ({reason}); check that the MLflow "
            "server is running and reachable from this machine (the limit is tracking.timeout_s)") from None
    _probed.add(uri)


def connect_timeout(timeout_s: float) -> int:
    """libpq's ``connect_timeout`` for tracking.timeout_s: whole seconds, at least 2 (libpq's own minimum)."""
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
        raise TrackingUnreachable(
            f"{what} {shown}: cannot connect within {limit} s ({urls.redact(_first_line(exc))}); check the "
            "host, port, database name and credentials, and that the server is running") from None
    try:
        conn.execute(text("SELECT pg_advisory_lock(:key)"), {"key": key})
        yield
    finally:  # closing the session releases the lock too (also when the block failed)
        conn.close()
        engine.dispose()


def _is_local_store(uri: str) -> bool:
    return uri.startswith(("sqlite:", "file:", "/", "postgresql", "mysql", "mssql")) or "://" not in uri


def experiment_id(client: MlflowClient, cfg: Config, name: str | None = None) -> str:
    """Get or create the config's experiment; concurrent creators agree on one id."""
    name = name or cfg.experiment_name
    exp = client.get_experiment_by_name(name)
    if exp is not None:
        return exp.experiment_id
    location = None
    if _is_local_store(cfg.paths.tracking_uri):
        location = cfg.paths.artifacts.as_uri()
    attempt = 0
    while True:
        try:
            return client.create_experiment(name, artifact_location=location, tags=EXPERIMENT_TAGS)
        except (MlflowException, SQLAlchemyError):  # another worker created it first (or is committing it)
            exp = client.get_experiment_by_name(name)
            if exp is not None:
                return exp.experiment_id
            attempt += 1
            if attempt == 3:
                raise
            time.sleep(0.2 * attempt)


def _git(args: list[str], cwd: Path | None) -> str:
    try:
        out = subprocess.run(["git", *args], cwd=cwd or Path(__file__).parent, capture_output=True, text=True,
                             timeout=5)
        return out.stdout.strip() if out.returncode == 0 else ""
    except (OSError, subprocess.SubprocessError):
        return ""


def mark_training_experiment(client: MlflowClient, exp_id: str) -> None:
    """Tag an experiment made before EXPERIMENT_TAGS existed, so MLflow 3's UI opens it on its runs table."""
    exp = client.get_experiment(exp_id)
    for key, value in EXPERIMENT_TAGS.items():
        if key not in exp.tags:
            client.set_experiment_tag(exp_id, key, value)


def git_commit(cwd: Path | None = None) -> str:
    return _git(["rev-parse", "HEAD"], cwd) or "unknown"


def source_name(argv: list[str] | None = None) -> str:
    """``bronchopose <command>`` when run through the CLI (also in its spawned workers), else the script's name."""
    argv = sys.argv if argv is None else argv
    path = Path(argv[0]) if argv and argv[0] else Path("python")
    prog = path.name
    if prog == "bronchopose" or path.parent.name == "bronchocli":  # the console script, or python -m bronchocli.cli
        command = next((a for a in argv[1:] if not a.startswith("-")), "")
        return f"bronchopose {command}".strip()
    return prog


def source_tags(cfg: Config) -> dict[str, str]:
    """MLflow's standard source fields; one that cannot be known (no git checkout) is left out, never empty."""
    tags = {TAG_SOURCE_NAME: source_name(), TAG_SOURCE_TYPE: "LOCAL"}
    for where in (cfg.paths.base, None):  # the config's checkout, else the code's own (an editable install)
        commit = git_commit(where)
        if commit != "unknown":
            tags[TAG_SOURCE_GIT] = commit
            branch = _git(["rev-parse", "--abbrev-ref", "HEAD"], where)
            if branch and branch != "HEAD":
                tags[TAG_SOURCE_BRANCH] = branch
            break
    return tags


def python_tags() -> dict[str, str]:
    """``env.python``; ``env.torch``/``env.cuda`` are logged by training (torch is not imported here)."""
    return {"env.python": platform.python_version()}


def non_empty(tags: Mapping[str, Any]) -> dict[str, str]:
    """Tags without the unknown ones: a missing tag reads as "" everywhere, an empty one only clutters the UI."""
    return {k: str(v) for k, v in tags.items() if v is not None and str(v) != ""}


def cell_tags(cfg: Config, cell: Cell, **extra: str) -> dict[str, str]:
    """A cell run's tags: coordinates, key, sweep, provenance, MLflow's source fields (no empty values)."""
    tags: dict[str, Any] = cell.tags()
    tags.update({
        TAG_CELL_KEY: cell.key,
        TAG_SWEEP: cfg.name,
        TAG_GIT: git_commit(cfg.paths.base),
        TAG_VERSION: __version__,
        TAG_HPARAMS: cfg.tune.applied or "config",
        TAG_KIND: "cell",
        "profile": cfg.profile,
        "mlflow.runName": cell.label.replace("/", "-"),
        **source_tags(cfg),
        **python_tags(),
    })
    tags.update(extra)
    return non_empty(tags)


def flatten(data: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """Nested config -> ``{"train.lr": "0.0001", ...}`` (lists as their JSON-ish repr)."""
    out: dict[str, str] = {}
    for key, value in data.items():
        path = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            out.update(flatten(value, f"{path}."))
        else:
            out[path] = str(value)
    return out


def log_params(client: MlflowClient, run_id: str, params: Mapping[str, str]) -> None:
    # URL-valued settings may carry a password: never store it in clear.
    items = [Param(k, urls.redact(v)[:6000]) for k, v in sorted(params.items())]
    for i in range(0, len(items), _PARAM_BATCH):
        client.log_batch(run_id, params=items[i : i + _PARAM_BATCH])


def log_metrics(client: MlflowClient, run_id: str, metrics: Mapping[str, float], step: int = 0) -> None:
    now = int(time.time() * 1000)
    items = [Metric(k, float(v), now, step) for k, v in metrics.items()]
    for i in range(0, len(items), 1000):
        client.log_batch(run_id, metrics=items[i : i + 1000])


def _quote(value: str) -> str:
    return "'" + value.replace("'", "\\'") + "'"


def search_runs(
    client: MlflowClient,
    experiment_ids: Iterable[str],
    tags: Mapping[str, str] | None = None,
    statuses: Iterable[str] | None = None,
    max_results: int = 50000,
) -> list[Run]:
    """Runs matching every tag (exact) and one of the statuses, newest first, in as few queries as possible."""
    clauses = [f"tags.{k} = {_quote(str(v))}" for k, v in (tags or {}).items()]
    statuses = list(statuses or [])
    if len(statuses) == 1:
        clauses.append(f"attributes.status = {_quote(statuses[0])}")
    runs: list[Run] = []
    token = None
    while True:
        page = client.search_runs(
            list(experiment_ids), " and ".join(clauses), max_results=min(max_results, 50000),
            order_by=["attributes.start_time DESC"], page_token=token,
        )
        runs.extend(page)
        token = page.token
        if not token or len(runs) >= max_results:
            break
    if len(statuses) > 1:
        runs = [r for r in runs if r.info.status in statuses]
    return runs
