"""Find and load a trained run's MLflow Model: by run id, registry URI, logged-model id or local folder.

References ``resolve`` understands (the MLflow store is the config's):

* a run id (32 hex digits), or ``runs:/<run_id>/model``;
* ``models:/<name>/<version>``, ``models:/<name>/latest``, ``models:/<name>@<alias>`` (Model Registry);
* ``models:/<model_id>`` (an MLflow 3 logged model, ``m-...``);
* a local folder holding an ``MLmodel`` file (a downloaded model).

A run without a model (``runs.model_artifact: none``, an unfinished run,
or one logged before MLflow Models, with a bare ``model/model.pt``) is one
``BronchoError`` line naming the run and why.
"""

from __future__ import annotations

import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit
from urllib.request import url2pathname

import mlflow
from mlflow.exceptions import MlflowException
from mlflow.models import Model

from ..errors import BronchoError
from ..training.bundle import LOADER, PREFIX
from ..training.model_logging import MODEL_NAME
from .mlflow_model import LEGACY_LOADER, PoseModel, load_data_dir

_RUN_ID = re.compile(r"^[0-9a-f]{32}$")


@dataclass(frozen=True)
class ModelRef:
    reference: str  # what the user gave
    run_id: str | None  # the training run, when known
    model_id: str | None  # the MLflow logged model, when known
    location: str  # artifact URI or local folder of the MLflow model


@dataclass(frozen=True)
class LoadedModel:
    model: PoseModel
    ref: ModelRef

    @property
    def label(self) -> str:
        spec = self.model.spec
        return spec.get("cell") or spec.get("arch", "model")


def _run_model(client, run_id: str, reference: str) -> ModelRef:
    try:
        run = client.get_run(run_id)
    except MlflowException:
        raise BronchoError(f"{reference}: no such MLflow run in {client.tracking_uri}") from None
    models = [m for m in _search_models(client, run.info.experiment_id) if m.source_run_id == run_id]
    ready = [m for m in models if str(getattr(m.status, "name", m.status)).upper().endswith("READY")]
    if ready:
        m = max(ready, key=lambda m: m.creation_timestamp or 0)
        return ModelRef(reference, run_id, m.model_id, m.artifact_location)
    names = {f.path for f in client.list_artifacts(run_id, MODEL_NAME)} if run.info.artifact_uri else set()
    if f"{MODEL_NAME}/MLmodel" in names:  # a model logged as plain run artifacts
        return ModelRef(reference, run_id, None, f"{run.info.artifact_uri.rstrip('/')}/{MODEL_NAME}")
    why = ("it logged only bare weights (model/model.pt, before runs logged MLflow Models): retrain it"
           if f"{MODEL_NAME}/model.pt" in names else
           f"its status is {run.info.status}" if run.info.status != "FINISHED" else
           "runs.model_artifact was none when it ran")
    raise BronchoError(f"run {run_id} has no MLflow model ({why})")


def _search_models(client, experiment_id: str):
    token = None
    while True:
        page = client.search_logged_models(experiment_ids=[experiment_id], filter_string=f"name = '{MODEL_NAME}'",
                                           page_token=token)
        yield from page
        token = page.token
        if not token:
            return


def _logged(client, model_id: str, reference: str) -> ModelRef:
    try:
        m = client.get_logged_model(model_id)
    except MlflowException:
        raise BronchoError(f"{reference}: no logged model {model_id} in {client.tracking_uri}") from None
    return ModelRef(reference, m.source_run_id, m.model_id, m.artifact_location)


def _registered(client, name: str, version: str | None, alias: str | None, reference: str) -> ModelRef:
    try:
        if alias is not None:
            mv = client.get_model_version_by_alias(name, alias)
        elif version == "latest":
            versions = client.search_model_versions(f"name = '{name}'")
            if not versions:
                raise MlflowException(f"no versions of {name}")
            mv = max(versions, key=lambda v: int(v.version))
        else:
            mv = client.get_model_version(name, str(version))
    except MlflowException:
        raise BronchoError(f"{reference}: no such registered model version in {client.tracking_uri} "
                           f"(registered: {', '.join(m.name for m in client.search_registered_models()) or 'none'})"
                           ) from None
    if getattr(mv, "model_id", None):
        ref = _logged(client, mv.model_id, reference)
        return ModelRef(reference, ref.run_id or mv.run_id, ref.model_id, ref.location)
    return ModelRef(reference, mv.run_id, None, mv.source)


def resolve(client, reference: str) -> ModelRef:
    """Where the MLflow model of ``reference`` lies (see the module doc)."""
    ref = reference.strip()
    if _RUN_ID.match(ref):
        return _run_model(client, ref, reference)
    m = re.match(r"^runs:/([0-9a-f]{32})/" + MODEL_NAME + r"/?$", ref)
    if m:
        return _run_model(client, m.group(1), reference)
    m = re.match(r"^models:/(m-[0-9a-f]+)/?$", ref)
    if m:
        return _logged(client, m.group(1), reference)
    m = re.match(r"^models:/([^/@]+)(?:/([^/]+)|@(.+))$", ref)
    if m:
        return _registered(client, m.group(1), m.group(2), m.group(3), reference)
    local = Path(ref).expanduser()
    if (local / "MLmodel").is_file():
        return ModelRef(reference, None, None, str(local.resolve()))
    raise BronchoError(f"model {reference!r}: not a run id, runs:/<run_id>/model, models:/<name>/<version>, "
                       "models:/<name>@<alias>, models:/<model_id> or a folder with an MLmodel file")


_BUNDLED = re.compile(re.escape(PREFIX) + r"[0-9a-f]+\." + LOADER)


def load_local(path: str | Path) -> PoseModel:
    """A downloaded MLflow model folder -> its PoseModel, built with this bronchocli's classes.

    Refuses a model bronchocli did not write. A model that carries its code (``<bundle>.portable``) and one
    logged before (``LEGACY_LOADER``) load the same way: only their ``data/`` folder is read.
    """
    path = Path(path)
    meta = Model.load(str(path / "MLmodel"))
    pyfunc = meta.flavors.get("python_function", {})
    loader = str(pyfunc.get("loader_module"))
    if loader != LEGACY_LOADER and not _BUNDLED.fullmatch(loader):
        raise BronchoError(f"{path}: not a bronchopose model (its pyfunc loader is {loader!r}, expected "
                           f"{PREFIX}<hash>.{LOADER} or {LEGACY_LOADER})")
    return load_data_dir(path / pyfunc["data"])


def _local_path(location: str) -> Path | None:
    if location.startswith("file:"):
        return Path(url2pathname(urlsplit(location).path))
    return None if "://" in location or location.startswith(("mlflow-artifacts:", "models:", "runs:")) else Path(location)


def load(client, reference: str) -> LoadedModel:
    """Resolve ``reference``, download the model (a local store's is read in place) and load it on the CPU."""
    ref = resolve(client, reference)
    local = _local_path(ref.location)
    if local is not None and local.is_dir():
        return LoadedModel(load_local(local), ref)
    with tempfile.TemporaryDirectory(prefix="bronchopose-model-") as tmp:
        try:
            local = mlflow.artifacts.download_artifacts(artifact_uri=ref.location, dst_path=tmp,
                                                        tracking_uri=client.tracking_uri)
        except MlflowException as exc:
            raise BronchoError(f"{reference}: cannot download the model from {ref.location} "
                               f"({str(exc).splitlines()[0]})") from None
        return LoadedModel(load_local(local), ref)


def register(client, ref: ModelRef, name: str) -> str:
    """Register the model of ``ref`` as a new version of registered model ``name``; returns the version."""
    try:
        client.create_registered_model(name)
    except MlflowException as exc:
        if "already exists" not in str(exc).lower() and "RESOURCE_ALREADY_EXISTS" not in str(exc):
            raise BronchoError(f"--register {name}: {str(exc).splitlines()[0]}") from None
    # The artifact location, not models:/<model_id>: MLflow resolves the latter through its global tracking URI.
    mv = client.create_model_version(name, ref.location, run_id=ref.run_id, model_id=ref.model_id)
    return str(mv.version)
