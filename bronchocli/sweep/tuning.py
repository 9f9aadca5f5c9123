"""Hyperparameter tuning with Optuna: one study per cell on the sweep's shared storage.

Each trial samples ``tune.space`` (dotted config paths -> distributions), trains
the cell with those values as one MLflow run (tagged ``run_kind=trial``, the
study and trial number) and returns the best validation loss, which the study
minimises. Per-epoch validation losses are reported to Optuna, whose pruner
(median or Hyperband) may stop a trial early: its run is KILLED and tagged
``pruned``. The study lives in ``storage.url`` (SQLite file or PostgreSQL), so
several processes or machines tune it together and an interrupted study
resumes where it stopped: ``--trials N`` is the total of finished (complete or
pruned) trials of the study, not of this process. Trials whose process died
are failed by Optuna's heartbeat and do not count; a trial stopped by a signal
hands its checkpoint to a trial of the same parameters that the next ``tune``
resumes (``tuneresume``).
"""

from __future__ import annotations

import logging
import math
import os
import re
import socket
import time
import warnings
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from functools import partial
from typing import Any, Callable, Mapping, Sequence

import optuna
from sqlalchemy import create_engine, inspect, make_url, text
from sqlalchemy.exc import ArgumentError, SQLAlchemyError
from sqlalchemy.pool import NullPool

from .. import extras, runkeys, urls
from ..cells import Cell
from ..config import Config, TuneParam, space_problems
from ..errors import BronchoError, ConfigError
from ..io import file_lock
from ..runs.client import MIGRATION_LOCK_KEY, client_for, connect_timeout, database_lock, experiment_id
from ..runs.contract import RunInterrupted, RunPruned
from ..runs.parents import study_parent
from ..runs.records import TAG_PARENT, run_name
from ..training.cost import COST_TARGET, cost_value
from .storage import StorageError
from .stagework import GPU_ENV
from .tuneresume import ATTR_RUN, keep_for_resume, resume_from, worth_resuming
from .worker import WorkerId

log = logging.getLogger(__name__)


class TrialFailed(BronchoError):
    """A trial's run FAILED (e.g. a non-finite loss); the study records it and goes on."""


OPTUNA_LOCK_KEY = MIGRATION_LOCK_KEY + 1  # pg_advisory_lock key of Optuna's table creation
ATTR_CELL = "cell"
ATTR_WORKER = "worker"  # the process (and GPU) that ran the trial, as a sweep's claims show a worker


def study_name(cfg: Config, cell: Cell) -> str:
    """The default study of a cell: everything of the cell except the hyperparameters being searched."""
    fold = f"-{cell.fold}" if cell.fold else ""
    size = f"-t{cell.train_trajectories}" if cell.train_trajectories else ""
    return f"{cfg.name}-{cell.arch}-{cell.rot_loss}-{cell.population}{fold}-{cell.pose_frame}-s{cell.seed}{size}"


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


def check_space(cfg: Config) -> None:
    """Every ``tune.space`` key must be a settable config path and every distribution well formed
    (``config.space_problems``, which loading a config already runs)."""
    problems = space_problems(cfg)
    if problems:
        raise ConfigError("invalid tune.space:\n  " + "\n  ".join(problems))


def suggest(trial, space: Mapping[str, TuneParam]) -> dict[str, Any]:
    values: dict[str, Any] = {}
    for path, p in space.items():
        if p.type == "float":
            values[path] = trial.suggest_float(path, p.low, p.high, log=p.log, step=p.step)
        elif p.type == "int":
            values[path] = trial.suggest_int(path, int(p.low), int(p.high), log=p.log, step=int(p.step or 1))
        else:
            values[path] = trial.suggest_categorical(path, p.choices)
    return values


# What a trial returns, per tune.objective: (the per-validation key reported to the pruner, the run's metric)
OBJECTIVES = {"val_loss": (runkeys.VAL_LOSS, runkeys.best_of(runkeys.VAL_LOSS)),
              "val_ratio": (runkeys.VAL_RATIO, runkeys.best_of(runkeys.VAL_RATIO)),
              # the cost of learning (training/cost.py): pairs seen until val.ratio.pos_l2 <= COST_TARGET; each
              # trial stops there (train.stop_at_ratio), its validations report the ratio to the pruner
              "cost": (runkeys.VAL_RATIO, runkeys.cost("pairs", COST_TARGET))}
ATTR_OBJECTIVE = "objective"  # the study's user attribute: the run metric its trials' values are


def objective_metric(cfg: Config) -> str:
    """The run metric a trial's value is (``val_best.loss`` or ``val_best.ratio.pos_l2``)."""
    return OBJECTIVES[cfg.tune.objective][1]


def _val_every_pairs(cfg: Config) -> int:
    return cfg.train.val_every * cfg.train.pairs_per_step


def budgeted(base: Config, trial_cfg: Config) -> Config:
    """A trial's config under ``tune.budget_pairs``: as many steps as the budget's pairs at the trial's pairs per
    step, validations every as many pairs as the study's base config validates at (``train.val_every`` x its pairs
    per step), so every trial is judged at the same pairs seen; ``trial_cfg`` itself without a budget."""
    budget = base.tune.budget_pairs
    if budget is None:
        return trial_cfg
    per_step = trial_cfg.train.pairs_per_step
    steps = max(1, math.ceil(budget / per_step))
    every = max(1, min(steps, round(_val_every_pairs(base) / per_step)))
    return trial_cfg.with_values({"train.steps": steps, "train.val_every": every})


def make_pruner(cfg: Config):
    """Trials report at optimiser steps (every train.val_every), or at pairs seen under tune.budget_pairs:
    the warm-up and the resources are in those units."""
    t = cfg.tune
    unit = _val_every_pairs(cfg) if t.budget_pairs is not None else cfg.train.val_every
    end = t.budget_pairs if t.budget_pairs is not None else cfg.train.steps
    if t.pruner == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=t.startup_trials,
                                           n_warmup_steps=t.warmup_validations * unit)
    if t.pruner == "hyperband":
        return optuna.pruners.HyperbandPruner(min_resource=max(1, t.warmup_validations) * unit, max_resource=end)
    return optuna.pruners.NopPruner()


def make_sampler(cfg: Config, worker: int = 0):
    seed = cfg.tune.seed + worker  # workers of one study must not propose identical first trials
    if cfg.tune.sampler == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    return optuna.samplers.TPESampler(seed=seed, n_startup_trials=cfg.tune.startup_trials)


def open_study(cfg: Config, cell: Cell, *, study: str | None = None, worker: int = 0):
    name = study or study_name(cfg, cell)
    s = optuna.create_study(study_name=name, storage=storage_for(cfg), direction="minimize",
                            sampler=make_sampler(cfg, worker), pruner=make_pruner(cfg), load_if_exists=True)
    metric = objective_metric(cfg)
    before = s.user_attrs.get(ATTR_OBJECTIVE)
    if before is not None and before != metric:  # trials of one study must minimise one thing
        raise ConfigError(f"tune.objective {cfg.tune.objective!r}: study {name!r} minimises {before} already; "
                          "keep its objective or name a new study (--study NAME)")
    s.set_user_attr("target", cell.tags())
    s.set_user_attr(ATTR_OBJECTIVE, metric)
    return s


TRIAL_SLOT_LOCK_KEY = MIGRATION_LOCK_KEY + 2  # pg_advisory_lock key of "is one more trial needed?"


@contextmanager
def trial_slot(cfg: Config) -> Iterator[None]:
    """Held while a worker counts the study's finished and running trials and starts one more: two processes
    (or machines) sharing a study otherwise both see N-1 trials and both start the N-th."""
    url = cfg.paths.storage_url
    if urls.is_postgres(url):
        with database_lock(url, cfg.runs.timeout_s, "storage.url", key=TRIAL_SLOT_LOCK_KEY):
            yield
        return
    db = urls.sqlite_file(url)
    if db is None:
        yield
        return
    with file_lock(f"{db}.trials.lock"):
        yield


def finished(study) -> int:
    return len(study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,
                                                         optuna.trial.TrialState.PRUNED)))


def _running(study) -> int:
    return len(study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)))


def study_parent_or_none(cfg: Config, target: Cell, name: str) -> str | None:
    """The study's parent MLflow run (trials nest under it); None when the MLflow store refused it."""
    try:
        client = client_for(cfg)
        return study_parent(client, cfg, experiment_id(client, cfg), name, target)
    except Exception as exc:  # noqa: BLE001 - nesting is cosmetic: trials must run without it
        log.warning("no parent run for study %s: %s", name, exc)
        return None


def objective(cfg: Config, target: Cell, name: str, progress: bool = False) -> Callable:
    """The function Optuna calls per trial: train one configured run, return ``tune.objective`` of the weights it
    tested (``objective_metric``); validations report the same quantity to the pruner, at optimiser steps or, under
    ``tune.budget_pairs``, at pairs seen."""
    from ..training.run import run_cell  # lazy: torch loads only where trials run, not for --show

    parent = study_parent_or_none(cfg, target, name)
    reported, metric = OBJECTIVES[cfg.tune.objective]

    def run(trial) -> float:
        run.release()  # this trial now counts as RUNNING: another process may decide whether it needs one more
        values = suggest(trial, cfg.tune.space)
        trial_cfg = budgeted(cfg, cfg.with_values(values))
        if cfg.tune.objective == "cost":  # a trial ends once it learned: the pairs it took are its value
            trial_cfg = trial_cfg.with_values({"train.stop_at_ratio": COST_TARGET})
        cell = trial_cfg.cell(**target.coords())
        per_step = trial_cfg.train.pairs_per_step if cfg.tune.budget_pairs is not None else 1
        trial.set_user_attr(ATTR_CELL, cell.key)
        trial.set_user_attr(ATTR_WORKER, str(WorkerId(socket.gethostname(), os.getpid(), gpu=os.environ.get(GPU_ENV))))

        def on_validation(step: int, metrics: dict[str, float]) -> None:
            value = metrics[reported]
            trial.report(value, step * per_step)
            if trial.should_prune():
                raise RunPruned(f"pruned by the {cfg.tune.pruner} pruner at step {step} ({reported} {value:.4g})")

        tags = {"run_kind": "trial", "study": name, "trial": str(trial.number),
                "mlflow.runName": f"trial-{trial.number} · {run_name(cell)}",
                "hparams_source": f"optuna:{name}#{trial.number}"}
        if parent is not None:
            tags[TAG_PARENT] = parent
        resume = resume_from(cfg, trial, cell.key, tags)  # a trial enqueued to continue a stopped one's run
        try:
            result = run_cell(trial_cfg, cell, resume=resume, extra_tags=tags, progress=progress,
                              on_validation=on_validation,
                              run_id_callback=lambda rid: trial.set_user_attr(ATTR_RUN, rid))
        except RunPruned as exc:
            raise optuna.TrialPruned(str(exc)) from None
        except BaseException as exc:  # stopped with a checkpoint: a new trial continues it (this one ends FAIL)
            if worth_resuming(exc):
                keep_for_resume(cfg, trial, trial.user_attrs.get(ATTR_RUN) or resume, cell.key)
            raise
        if result.status != "FINISHED":
            raise TrialFailed(f"trial {trial.number} failed: {result.failure_reason}")
        if result.stop_requested:  # Ctrl-C during the trial's last steps (evaluation): the trial counts, none follows
            run.stop_requested = (trial.number, result.stop_requested)
        value = cost_value(result.metrics) if cfg.tune.objective == "cost" else result.metrics.get(metric, math.nan)
        if not math.isfinite(value):
            raise TrialFailed(f"trial {trial.number}: no finite {metric}")
        return value

    run.stop_requested = None  # (trial number, signal) once a stop request arrived while a trial evaluated
    run.release = lambda: None  # tune_worker's trial slot (``trial_slot``), released when the trial starts
    return run


def tune_worker(cfg: Config, target: Cell, trials: int, *, study: str | None = None,
                timeout: float | None = None, worker: int = 0, progress: bool = False,
                enqueue: Sequence[Mapping[str, Any]] = (), stop: Callable[[], bool] = lambda: False) -> int:
    """Run trials of the study until it holds ``trials`` finished ones (or the timeout, or ``stop()``: a stop
    request that arrived between trials); returns trials run here."""
    s = open_study(cfg, target, study=study, worker=worker)
    for params in enqueue:
        s.enqueue_trial(dict(params), skip_if_exists=True)
    fn = objective(cfg, target, s.study_name, progress)
    deadline = None if timeout is None else time.monotonic() + timeout
    ran = 0
    # A trial that fails (not pruned) is retried by the next iteration; three in a row stop this worker.
    failures = 0
    while failures < 3 and not stop():
        if deadline is not None and time.monotonic() >= deadline:
            break
        slot = ExitStack()  # deciding that one more trial is needed and creating it: one step across processes
        slot.enter_context(trial_slot(cfg))
        if finished(s) + _running(s) >= trials:
            slot.close()
            break
        fn.release = slot.close  # the objective releases the slot once its trial exists (RUNNING in the storage)
        before = finished(s)
        try:
            s.optimize(fn, n_trials=1, catch=(TrialFailed,))
        finally:
            slot.close()  # idempotent: released already unless the trial never started
        if fn.stop_requested is not None:
            number, signum = fn.stop_requested
            raise RunInterrupted(f"tune interrupted (signal {signum} while trial #{number} was evaluated: that trial "
                                 "was completed first, no other was started); run the same command to continue")
        last = s.get_trials(deepcopy=False)[-1]
        if last.state == optuna.trial.TrialState.FAIL:
            log.warning("trial %d failed (its MLflow run %s says why)", last.number, last.user_attrs.get(ATTR_RUN))
        ran += 1
        failures = 0 if finished(s) > before else failures + 1
    return ran


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
                           "objective": s.user_attrs.get(ATTR_OBJECTIVE, OBJECTIVES["val_loss"][1])}
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
