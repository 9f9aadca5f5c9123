"""Copied or moved projects: point an experiment's artifact locations at ``runs.artifacts``.

MLflow stores absolute artifact locations, so a copied (``cp -a``) or moved project would otherwise write
into, and report from, the original's folder. The runs' dataset inputs (their source is the dataset folder's
absolute ``file:`` URI) move along the same way when the dataset lay inside the moved project.
"""

from __future__ import annotations

import json
import urllib.parse
import urllib.request
from pathlib import Path

from mlflow.tracking import MlflowClient
from sqlalchemy import create_engine, text
from sqlalchemy import inspect as sqlalchemy_inspect
from sqlalchemy.pool import NullPool

from .. import urls
from ..config import Config
from ..errors import BronchoError
from .records import search_runs


class ArtifactsElsewhere(BronchoError):
    """The experiment's artifacts are not where the config's ``runs.artifacts`` says."""


def _local_path(location: str) -> Path | None:
    """The folder of a ``file:`` URI or a plain path; None for remote artifact stores (s3://, mlflow-artifacts:)."""
    if location.startswith("file:"):
        return Path(urllib.request.url2pathname(urllib.parse.urlparse(location).path))
    if location and "://" not in location and not location.startswith("mlflow-artifacts:"):
        return Path(location)
    return None


def writes_here(cfg: Config, artifact_uri: str) -> bool:
    """Whether a run's artifacts (``artifact_uri``) are written into this project: under ``runs.artifacts`` for
    a store the project holds itself, anywhere an MLflow server decides otherwise."""
    if urls.is_server(cfg.paths.mlflow_uri) or not urls.is_direct_store(cfg.paths.mlflow_uri):
        return True
    where = _local_path(artifact_uri)
    return where is None or where.resolve().is_relative_to(cfg.paths.artifacts.resolve())


def relocate_artifacts(client: MlflowClient, cfg: Config, *, rewrite: bool, reading: bool = False) -> None:
    """Point the config's experiment (and its runs and models) at ``runs.artifacts`` when it points elsewhere.

    MLflow stores absolute artifact locations, so a copied (``cp -a``) or moved
    project would otherwise write into, and report from, the original's folder,
    and a changed ``runs.artifacts`` would be ignored. When the store is a
    project's own SQLite file (``rewrite``) and the runs' artifacts are under the
    configured folder (a copy or a move), or nowhere any more, or there are no
    runs, the locations are rewritten. Otherwise (a database shared with
    another folder, or artifacts that still live only in the old place) it
    refuses in one line naming both folders and the fix, before anything runs
    (``reading``: reports and status read the artifacts where they are instead).
    """
    uri = cfg.paths.mlflow_uri
    if urls.is_server(uri) or not urls.is_direct_store(uri):
        return  # an MLflow server decides where artifacts go
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
    fix = ("this copy shares the MLflow database with the original: set runs.experiment to a new name here, "
           f"or runs.artifacts={have}" if not rewrite else
           f"move the folder there (mv {have} {want}), set runs.artifacts={have}, or use a new runs.experiment")
    raise ArtifactsElsewhere(f"MLflow experiment {cfg.experiment_name!r} keeps its artifacts in {have} but "
                             f"runs.artifacts is {want}; {fix}")


def moved_roots(have: Path, want: Path) -> tuple[Path, Path]:
    """The folders a project moved between, from its old and new artifact folders: their common trailing part
    removed (``/a/orig/runs/artifacts`` -> ``/b/copy/runs/artifacts`` gives ``/a/orig``, ``/b/copy``)."""
    h, w = have.parts, want.parts
    n = 0
    while n < min(len(h), len(w)) - 1 and h[-1 - n] == w[-1 - n]:
        n += 1
    return Path(*h[: len(h) - n]), Path(*w[: len(w) - n])


def relocated_source(source: str, old_root: Path, new_root: Path) -> str | None:
    """A dataset input's source (MLflow's JSON ``{"uri": "file://..."}``) moved with the project: the same
    folder under ``new_root`` when it lay under ``old_root`` and exists there; None to leave it as it is (a
    dataset outside the project, or not copied with it)."""
    try:
        data = json.loads(source)
    except ValueError:
        return None
    where = _local_path(data.get("uri", "")) if isinstance(data, dict) else None
    if where is None or not where.is_relative_to(old_root):
        return None
    moved = new_root / where.relative_to(old_root)
    if moved == where or not moved.exists():
        return None
    return json.dumps({**data, "uri": moved.as_uri()})


def _rewrite_sources(conn, experiment: int | str, old: str, new: str) -> None:
    """Point the experiment's local dataset inputs that moved with the project at the new copy."""
    old_root, new_root = moved_roots(_local_path(old), _local_path(new))
    rows = conn.execute(text("SELECT dataset_uuid, dataset_source FROM datasets WHERE experiment_id = :exp AND "
                             "dataset_source_type = 'local'"), {"exp": experiment}).all()
    for uuid, source in rows:
        moved = relocated_source(source, old_root, new_root)
        if moved is not None:
            conn.execute(text("UPDATE datasets SET dataset_source = :src WHERE dataset_uuid = :id AND "
                              "experiment_id = :exp"), {"src": moved, "id": uuid, "exp": experiment})


def _rewrite_locations(uri: str, experiment: str, old: str, new: str) -> None:
    """Replace the ``old`` artifact-location prefix with ``new`` in one experiment's rows, and move its dataset
    inputs' sources along when they lay in the moved project (one transaction)."""
    old, new = old.rstrip("/"), new.rstrip("/")
    statements = [
        ("experiments", "artifact_location", "experiment_id"),
        ("runs", "artifact_uri", "experiment_id"),
        ("logged_models", "artifact_location", "experiment_id"),
    ]
    exp = int(experiment) if experiment.isdigit() else experiment
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
                    {"new": new, "n": len(old) + 1, "exp": exp, "old": old, "m": len(old) + 1, "prefix": old + "/"})
            if "datasets" in tables and _local_path(old) is not None and _local_path(new) is not None:
                _rewrite_sources(conn, exp, old, new)
    finally:
        engine.dispose()
