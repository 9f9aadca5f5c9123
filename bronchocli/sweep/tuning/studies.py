"""Optuna studies on the shared storage: where their tables live, opening the storage, reading a study back.

A study lives in ``storage.url`` (SQLite file or PostgreSQL) beside the claims
table, in a schema (or file) of its own when that is MLflow's database too
(``optuna_url``). Reading a study (``load``, ``describe_study``,
``best_values``) creates nothing; ``storage_for`` creates Optuna's tables once
(under a lock: machines race for it). What a trial does: ``trial``; how
trials are claimed and run: ``launch`` and ``worker``.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from functools import partial
from typing import Any

import optuna
from sqlalchemy import create_engine, inspect, make_url, text
from sqlalchemy.exc import ArgumentError, SQLAlchemyError
from sqlalchemy.pool import NullPool

from ... import extras, runkeys, urls
from ...config import Config
from ...errors import BronchoError
from ...io import file_lock
from ...runs.client import MIGRATION_LOCK_KEY, connect_timeout, database_lock
from ..storage import StorageError
from .resume import ATTR_RUN


OPTUNA_LOCK_KEY = MIGRATION_LOCK_KEY + 1  # pg_advisory_lock key of Optuna's table creation
ATTR_OBJECTIVE = "objective"  # the study's user attribute: the run metric its trials' values are
DEFAULT_OBJECTIVE = runkeys.best_of(runkeys.VAL_LOSS)  # a study's objective where it names none (older studies)

# Optuna logs a failed trial as a warning with a traceback; the reason is in the trial's MLflow run instead.
optuna.logging.set_verbosity(optuna.logging.ERROR)
# heartbeats are "experimental" in Optuna's API but are what makes dead trials fail cleanly
warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)


OPTUNA_SCHEMA = "bronchopose_optuna"  # Optuna's PostgreSQL schema when storage.url is MLflow's database


def _same_database(a: str, b: str) -> bool:
    """True when two URLs name one database (same SQLite file; same PostgreSQL host, port, database and options)."""
    fa, fb = urls.sqlite_file(a), urls.sqlite_file(b)
    if fa is not None or fb is not None:
        return fa is not None and fb is not None and fa.resolve() == fb.resolve()
    if not (urls.is_postgres(a) and urls.is_postgres(b)):
        return False
    try:
        ua, ub = make_url(urls.sqlalchemy(a)), make_url(urls.sqlalchemy(b))
    except ArgumentError:
        return False
    key = lambda u: (u.host or "localhost", u.port or 5432, u.database, u.query.get("options"))  # noqa: E731
    return key(ua) == key(ub)


def _holds_mlflow(url: str, timeout_s: float) -> bool:
    """True when the database already holds MLflow's tables (and not Optuna's): another spelling of runs.uri."""
    db = urls.sqlite_file(url)
    if db is not None and not db.is_file():
        return False
    engine = create_engine(url, poolclass=NullPool, **_connect_kwargs(url, timeout_s))
    try:
        with engine.connect() as conn:
            names = set(inspect(conn).get_table_names())
    except SQLAlchemyError:
        return False  # unreachable: storage_for says so in one line when it connects
    finally:
        engine.dispose()
    return {"experiments", "runs", "alembic_version"} <= names and "studies" not in names


def optuna_url(cfg: Config, probe: bool = True) -> str:
    """Where Optuna's tables live: ``storage.url``, unless that is MLflow's database too.

    MLflow and Optuna both record their schema revision in a table named
    ``alembic_version``, so they cannot share one schema. On PostgreSQL Optuna
    then gets a schema of its own in the same database (``bronchopose_optuna``,
    or ``<schema>_optuna`` beside a ``search_path`` given in the URL); on SQLite
    a file beside the database (``mlflow.db`` -> ``mlflow.optuna.db``). The
    claims table has no migration bookkeeping and stays in ``storage.url``.
    ``probe``: also look into the database for MLflow's tables (the same
    database spelled differently, e.g. ``localhost`` and ``127.0.0.1``).
    """
    url = cfg.paths.storage_url
    if not _same_database(url, cfg.paths.mlflow_uri) and not (
            probe and _holds_mlflow(urls.sqlalchemy(url), cfg.runs.timeout_s)):
        return url
    db = urls.sqlite_file(url)
    if db is not None:
        return f"sqlite:///{db.with_name(f'{db.stem}.optuna{db.suffix}')}"
    u = make_url(urls.sqlalchemy(url))
    options = u.query.get("options") or ""
    options = options[0] if isinstance(options, tuple) else options
    m = re.search(r"search_path\s*=\s*([\w$]+)", options)
    schema = f"{m.group(1)}_optuna" if m else OPTUNA_SCHEMA
    options = (re.sub(r"-c\s*search_path\s*=\s*[\w$,]+", "", options) + f" -csearch_path={schema}").strip()
    return u.update_query_dict({"options": options}).render_as_string(hide_password=False)


def _connect_kwargs(url: str, timeout_s: float) -> dict[str, Any]:
    if url.startswith("sqlite"):
        return {"connect_args": {"timeout": 60}}
    if urls.is_postgres(url):  # an unreachable server fails within runs.timeout_s
        return {"connect_args": {"connect_timeout": connect_timeout(timeout_s)}}
    return {}


def _create_schema(url: str) -> None:
    """The PostgreSQL schema named by the URL's search_path (``optuna_url``), created once (under the lock)."""
    u = make_url(url)
    m = re.search(r"search_path=([\w$]+)", str(u.query.get("options") or ""))
    if m is None:
        return
    engine = create_engine(u.difference_update_query(["options"]), poolclass=NullPool)
    try:
        with engine.begin() as conn:
            conn.execute(text(f'CREATE SCHEMA IF NOT EXISTS "{m.group(1)}"'))
    finally:
        engine.dispose()


def storage_for(cfg: Config):
    """Optuna RDB storage (``optuna_url``) with heartbeats for dead trials; StorageError (one line) if unreachable."""
    # a database server is looked into only once it answered (below): an unreachable one costs one timeout
    url = urls.sqlalchemy(optuna_url(cfg, probe=urls.sqlite_file(cfg.paths.storage_url) is not None))
    kwargs = _connect_kwargs(url, cfg.runs.timeout_s)
    beat = max(1, int(cfg.sweep.heartbeat_s))
    make = partial(optuna.storages.RDBStorage, engine_kwargs=kwargs, heartbeat_interval=beat,
                   grace_period=max(beat * 2, int(cfg.sweep.stale_after_s)))
    if urls.is_postgres(url):
        extras.require("postgres", f"storage.url {urls.redact(url)}")
    try:
        db = urls.sqlite_file(url)
        if urls.is_postgres(url):  # table creation must not race between machines either
            with database_lock(url, cfg.runs.timeout_s, "storage.url", key=OPTUNA_LOCK_KEY):
                url = urls.sqlalchemy(optuna_url(cfg))
                if url != urls.sqlalchemy(cfg.paths.storage_url):
                    _create_schema(url)
                return make(url)
        if db is None:
            return make(url)
        urls.check_sqlite(db, "storage.url")  # a damaged file: one line naming it, not Optuna's traceback
        db.parent.mkdir(parents=True, exist_ok=True)
        with file_lock(f"{db}.lock"):  # table creation must not race
            return make(url)
    except (SQLAlchemyError, ImportError, ValueError) as exc:
        text = str(getattr(exc, "orig", None) or exc).strip().splitlines()
        raise StorageError(f"storage.url {urls.redact(url)}: {urls.redact(text[0] if text else type(exc).__name__)}"
                           ) from None


@contextmanager
def storage_errors(cfg: Config) -> Iterator[None]:
    """Optuna's failures of the study storage (``StorageInternalError``: a read-only or damaged file, a server
    gone) as one line naming the storage, as the claims table says them (``SweepStore``), not Optuna's trace."""
    try:
        yield
    except optuna.exceptions.StorageInternalError as exc:
        cause = exc.__cause__ or exc.__context__ or exc
        if (damaged := urls.damaged_message(exc)) is not None:
            raise StorageError(damaged) from exc
        raise StorageError(f"study storage {urls.redact(optuna_url(cfg, probe=False))}: {urls.error_line(cause)}"
                           ) from exc


def _no_storage(cfg: Config) -> bool:
    """The studies' SQLite file does not exist: nothing to read (and reading must not create it)."""
    db = urls.sqlite_file(optuna_url(cfg, probe=False))
    return db is not None and not db.is_file()


def load(cfg: Config, name: str):
    """An existing study (BronchoError naming the studies there when it is not); creates nothing."""
    if _no_storage(cfg):
        raise BronchoError(f"no Optuna study named {name!r}: storage {urls.redact(cfg.paths.storage_url)} holds no "
                           "study yet (run `bronchopose tune` first)")
    storage = storage_for(cfg)
    try:
        return optuna.load_study(study_name=name, storage=storage)
    except KeyError:
        names = sorted(s.study_name for s in optuna.get_all_study_summaries(storage))
        raise BronchoError(f"no Optuna study named {name!r} in storage {urls.redact(cfg.paths.storage_url)} "
                           f"(studies there: {', '.join(names) or 'none'})") from None


def best_values(cfg: Config, name: str) -> tuple[dict[str, Any], str]:
    """The best finished trial's parameters (dotted config paths) and a provenance string."""
    s = load(cfg, name)
    try:
        best = s.best_trial
    except ValueError:
        raise BronchoError(f"study {name!r} has no completed trial yet") from None
    return dict(best.params), f"optuna:{name}#{best.number}"


def apply_best(cfg: Config, name: str) -> Config:
    """``cfg`` with the study's best parameters set and ``tune.applied`` recording where they came from."""
    values, source = best_values(cfg, name)
    return cfg.with_values({**values, "tune.applied": source})


def summary(cfg: Config, name: str) -> dict[str, Any]:
    """Counts, best trial and parameter importances of a study (for ``tune --show``)."""
    return describe_study(load(cfg, name))


def describe_study(s) -> dict[str, Any]:
    """Counts, best trial and parameter importances of a loaded study."""
    name = s.study_name
    states = optuna.trial.TrialState
    trials = s.get_trials(deepcopy=False)
    counts = {st.name.lower(): sum(t.state == st for t in trials) for st in states}
    out: dict[str, Any] = {"study": name, "counts": counts, "best": None, "importances": {},
                           "objective": s.user_attrs.get(ATTR_OBJECTIVE, DEFAULT_OBJECTIVE)}
    complete = [t for t in trials if t.state == states.COMPLETE]
    if complete:
        b = s.best_trial
        out["best"] = {"number": b.number, "value": b.value, "params": b.params,
                       "run_id": b.user_attrs.get(ATTR_RUN)}
    if len(complete) >= 2 and len(s.best_trial.params) > 0:
        try:
            out["importances"] = dict(optuna.importance.get_param_importances(s))
        except (RuntimeError, ValueError) as exc:  # e.g. every trial with the same value
            out["importances_note"] = str(exc)
    return out


def list_studies(cfg: Config) -> list[str]:
    if _no_storage(cfg):
        return []
    return sorted(s.study_name for s in optuna.get_all_study_summaries(storage_for(cfg)))


FINISHED_STATES = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)  # a trial that counts


def finished(study) -> int:
    """The study's finished trials: complete or pruned."""
    return len(study.get_trials(deepcopy=False, states=FINISHED_STATES))
