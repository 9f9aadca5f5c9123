"""MLflow conventions: store set-up, experiment, run tags and params, metric names, run lookup.

One MLflow run per grid cell. Runs are found again by their tags (``cell_key``,
``sweep``, ...), never by name. Everything goes through an explicit
``MlflowClient`` (no fluent global state), so one process can drive many runs.
"""

from __future__ import annotations

import logging
import os
import subprocess
import time
from pathlib import Path
from typing import Any, Iterable, Mapping

os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")  # before mlflow is imported
os.environ.setdefault("DO_NOT_TRACK", "true")

from mlflow.entities import Metric, Param, Run
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from . import __version__, urls
from .cells import FIELDS, Cell
from .config import Config
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
TAG_KIND = "run_kind"  # "cell" (train/sweep) or "trial" (tune)

_PARAM_BATCH = 100  # MLflow's limit of params per log_batch call


def _quiet() -> None:
    for name in ("mlflow", "alembic", "urllib3"):
        logging.getLogger(name).setLevel(logging.WARNING)


def redacted_uri(cfg: Config) -> str:
    """The tracking URI as it may be printed (password hidden)."""
    return urls.redact(cfg.paths.tracking_uri)


def client_for(cfg: Config) -> MlflowClient:
    _quiet()  # mlflow configures its own loggers when it is first used
    uri = cfg.paths.tracking_uri
    db = urls.sqlite_file(uri)
    if db is None:
        return MlflowClient(tracking_uri=uri)
    # MLflow creates (migrates) its tables when it opens a store; two processes doing that at once collide.
    with file_lock(f"{db}.lock"):
        client = MlflowClient(tracking_uri=uri)
        client.search_experiments(max_results=1)
    return client


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
    try:
        return client.create_experiment(name, artifact_location=location)
    except MlflowException:  # another worker created it first
        exp = client.get_experiment_by_name(name)
        if exp is None:
            raise
        return exp.experiment_id


def git_commit(cwd: Path | None = None) -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=cwd or Path(__file__).parent, capture_output=True, text=True, timeout=5
        )
        return out.stdout.strip() if out.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def cell_tags(cfg: Config, cell: Cell, **extra: str) -> dict[str, str]:
    tags = cell.tags()
    tags.update({
        TAG_CELL_KEY: cell.key,
        TAG_SWEEP: cfg.name,
        TAG_GIT: git_commit(cfg.paths.base),
        TAG_VERSION: __version__,
        TAG_HPARAMS: cfg.tune.applied or "config",
        TAG_KIND: "cell",
        "profile": cfg.profile or "",
        "mlflow.runName": cell.label.replace("/", "-"),
    })
    tags.update(extra)
    return tags


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
