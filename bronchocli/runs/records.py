"""What a run records in MLflow and how runs are found again: tags, params, metrics, search by tags.

One MLflow run per grid cell. Runs are found again by their tags (``cell_key``, ``sweep``, ...), never by
name. Everything goes through an explicit ``MlflowClient`` (no fluent global state), so one process can
drive many runs.
"""

from __future__ import annotations

import math
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterable, Mapping

from mlflow.entities import Metric, Param, Run, RunTag, ViewType
from mlflow.tracking import MlflowClient

from .. import __version__, registry, urls
from ..cells import FIELDS, Cell
from ..config import Config

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


def _git(args: list[str], cwd: Path | None) -> str:
    try:
        out = subprocess.run(["git", *args], cwd=cwd or Path(__file__).parent, capture_output=True, text=True,
                             timeout=5)
        return out.stdout.strip() if out.returncode == 0 else ""
    except (OSError, subprocess.SubprocessError):
        return ""


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


POPULATION_SHORT = {"personalized": "pers", "cross-subject": "xs"}


def run_title(arch: str, rot_loss: str, population: str, fold: str | None, seed: object, pose_frame: str,
              train_trajectories: object = None, backbone: str | None = None, init: str | None = None) -> str:
    """A cell run's name wherever one run is named (the UI's run name, ``status``, the report's figure legends):
    the model's name (``registry.model_name``), its seed, then the coordinates that tell its runs apart:
    ``BronchoTrack · s0 · pers · world``, ``+LSTM MSE+DE · s3 · xs-p01 · camera · t5`` (cross-subject: the test
    patient; ``t5``: a training-set size). Model and seed first: a column that cuts the name off still shows
    them."""
    parts = [registry.model_name(arch, rot_loss, backbone, init), f"s{seed}",
             POPULATION_SHORT.get(population, population) + (f"-{fold}" if fold else ""), pose_frame]
    if train_trajectories not in (None, ""):
        parts.append(f"t{train_trajectories}")
    return " · ".join(parts)


def backbone_of(cfg: Config) -> str | None:
    """The config's backbone (``model.backbone``; None before the key exists: the paper's)."""
    return getattr(cfg.model, "backbone", None)


def run_name(cell: Cell, backbone: str | None = None, init: str | None = None) -> str:
    """The cell as a run name (``run_title``); the full coordinates are in the description."""
    return run_title(cell.arch, cell.rot_loss, cell.population, cell.fold, cell.seed, cell.pose_frame,
                     cell.train_trajectories, backbone, init)


def run_title_of(tags: Mapping[str, str], params: Mapping[str, str]) -> str:
    """A logged cell run's name from its tags (the cell's coordinates, ``init``) and params (the backbone)."""
    return run_title(*(tags.get(k, "") or "" for k in FIELDS), backbone=params.get(registry.BACKBONE_PARAM),
                     init=tags.get(TAG_INIT))


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
        "mlflow.runName": run_name(cell, backbone_of(cfg), extra.get(TAG_INIT)),
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


def redacted(params: Mapping[str, str]) -> dict[str, str]:
    """Params as MLflow stores them: URL-valued settings may carry a password, never stored in clear."""
    return {k: urls.redact(v)[:6000] for k, v in sorted(params.items())}


def log_params(client: MlflowClient, run_id: str, params: Mapping[str, str]) -> None:
    items = [Param(k, v) for k, v in redacted(params).items()]
    for i in range(0, len(items), _PARAM_BATCH):
        client.log_batch(run_id, params=items[i : i + _PARAM_BATCH])


def set_tags(client: MlflowClient, run_id: str, tags: Mapping[str, Any]) -> None:
    """Set ``tags`` on a run that other processes may be tagging at the same moment (a sweep's parent, tagged by
    every worker as it starts). One batch: MLflow's SQL store writes a batch's tags again when another process
    inserted the same tag first, where ``set_tag`` fails on the unique key (``tag_pk``)."""
    if tags:
        client.log_batch(run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])


def log_metrics(client: MlflowClient, run_id: str, metrics: Mapping[str, float], step: int = 0,
                model_id: str | None = None, dataset: tuple[str, str] | None = None) -> None:
    """Metrics of the run at ``step``; with ``model_id`` also of that logged model, evaluated on ``dataset``
    (name, digest: the model's page lists it under "Datasets used"). A NaN stays the run's only: MLflow would
    store it as 0 for the model."""
    now = int(time.time() * 1000)
    name, digest = dataset or (None, None)
    items = [Metric(k, float(v), now, step) if model_id is None or math.isnan(float(v)) else
             Metric(k, float(v), now, step, model_id=model_id, dataset_name=name, dataset_digest=digest)
             for k, v in metrics.items()]
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
    deleted: bool = False,
) -> list[Run]:
    """Runs matching every tag (exact) and one of the statuses, newest first, in as few queries as possible
    (``deleted``: only the runs deleted by hand, which MLflow keeps until garbage-collected)."""
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
            **({"run_view_type": ViewType.DELETED_ONLY} if deleted else {}),
        )
        runs.extend(page)
        token = page.token
        if not token or len(runs) >= max_results:
            break
    if len(statuses) > 1:
        runs = [r for r in runs if r.info.status in statuses]
    return runs


def finished_cell_runs(client: MlflowClient, experiment_id: str, sweep: str,
                       keys: Iterable[str] | None = None) -> dict[str, Run]:
    """The newest FINISHED cell run (``run_kind=cell``, not a tuning trial) of each cell key of ``sweep``
    (``keys``: only these): MLflow is the record of what finished, whatever the claims table says."""
    want = None if keys is None else set(keys)
    tags = {TAG_SWEEP: sweep, TAG_KIND: "cell"}
    if want is not None and len(want) == 1:
        tags[TAG_CELL_KEY] = next(iter(want))
    out: dict[str, Run] = {}
    for run in search_runs(client, [experiment_id], tags, ["FINISHED"]):  # newest first
        key = run.data.tags.get(TAG_CELL_KEY)
        if key and (want is None or key in want):
            out.setdefault(key, run)
    return out


def deleted_cell_runs(client: MlflowClient, experiment_id: str, sweep: str) -> dict[str, Run]:
    """The newest deleted (by hand, in the MLflow UI) cell run of each cell key of ``sweep`` that has one."""
    out: dict[str, Run] = {}
    for run in search_runs(client, [experiment_id], {TAG_SWEEP: sweep, TAG_KIND: "cell"}, deleted=True):
        if key := run.data.tags.get(TAG_CELL_KEY):
            out.setdefault(key, run)
    return out


def deleted_runs_line(n: int, sweep: str, experiment: str, now: bool = False) -> str:
    """The one line for cell runs deleted by hand: ``status``, ``sweep`` and ``report`` all give it (``now``: the
    sweep that says it trains those cells again)."""
    head = f"{n} cell run(s) of sweep {sweep!r} in MLflow experiment {experiment!r} were deleted (in the MLflow UI)"
    if now:
        return f"{head}: their cells are not done, and this sweep trains them again"
    return (f"{head}: restore them there (the runs list, 'deleted') to keep them, or `bronchopose sweep run` trains "
            "those cells again")
