"""The MLflow Model a FINISHED run logs: a ``python_function`` model over the run's weights.

What ``model/`` holds (an MLflow 3 logged model named ``model`` whose source
run is the training run, so ``runs:/<run_id>/model`` and ``models:/<model_id>``
both find it, and ``mlflow.register_model`` can register it):

* ``MLmodel``: the ``python_function`` flavour whose loader module is the
  model's own code, ``code/bronchopose_model_<hash>/`` (``bundle.py``: copies of
  ``models/portable.py`` and the architecture's model modules), so loading
  needs only torch and MLflow, not bronchocli; a signature and an input example
  (two real test frames of the run); ``requirements.txt`` lists what that code
  imports (MLflow, torch, numpy, Pillow);
* ``data/bronchopose/weights.pt``: the network's state dict (fp16 or fp32, per
  ``runs.model_artifact``), loadable with ``torch.load(weights_only=True)``;
* ``data/bronchopose/spec.json``: what prediction needs besides the weights
  (architecture and its class in the bundle, input size, pose frame, units,
  chunk length, image normalisation, label standardisation, the training-mean
  relative pose).

The logged model is named ``model`` whatever its cell (``runs:/<run_id>/model`` finds it by that name); its tags
say the cell (``model_tags``: ``cell``, the label, and the run's description as the model's, which its page
shows). Its other fields: the run's params (``runs.views.run_params`` and the evaluation's constants) and,
logged by ``artifacts.log_outcome`` with the model's id, the run's test metrics
linked to the test split's dataset, so its page in the UI shows both.

Input: uint8 frames ``[T, H, W, 3]`` (RGB, channel last, one video in time
order, T >= 2). Output: ``float64 [T-1, 6]`` relative poses between
consecutive frames in the run's pose frame, in voxels and degrees (intrinsic
XYZ Euler). Frames of another size are resized (bilinear, as the frame cache
does when ``data.image_size`` differs from the dataset's) with one warning.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import tempfile
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import PIL
import torch
from mlflow.entities import LoggedModelOutput
from mlflow.models import Model, ModelSignature
from mlflow.types import Schema, TensorSpec

from .. import __version__, registry
from ..cells import Cell
from ..config import Config
from ..models.portable import SPEC_FILE, WEIGHTS_FILE
from ..runs.records import TAG_INIT, TAG_NOTE, backbone_of, redacted
from ..runs.views import describe
from . import bundle, evaluate
from .engine import EVAL_CHUNK, Outcome
from .network import export
from .prepare import RunData

log = logging.getLogger(__name__)

MODEL_NAME = "model"  # runs:/<run_id>/model
MODEL_NAME_TAG = "model_name"  # the logged model's tag with the model's one name (registry.model_name)
DATA_DIR = "bronchopose"  # MLflow copies it to model/data/bronchopose/ (SPEC_FILE and WEIGHTS_FILE)
SPEC_FORMAT = "bronchopose-pyfunc"
SPEC_VERSION = 1
INPUT_LAYOUT = "uint8 [T, H, W, 3]: T RGB frames of one video in time order, channel last (T >= 2)"
OUTPUT_LAYOUT = "float64 [T-1, 6]: relative pose frame t-1 -> t (dx, dy, dz in voxels; rx, ry, rz in degrees)"


def model_spec(cfg: Config, cell: Cell, data: RunData, outcome: Outcome, run_id: str) -> dict[str, Any]:
    """The JSON next to the weights: everything prediction needs besides them, and what the numbers mean."""
    net = outcome.network
    return {
        "format": SPEC_FORMAT, "version": SPEC_VERSION,
        "arch": cell.arch, "model_class": bundle.bundle_for(cell.arch).model_class,  # the class in code/
        "image_size": int(data.image_size), "temporal": bool(net.temporal),
        "chunk": int(cfg.data.window if net.temporal else EVAL_CHUNK),  # pairs per forward, as evaluation ran
        "pose_frame": cell.pose_frame, "units": {"position": "voxels", "rotation": "degrees (intrinsic XYZ Euler)"},
        "input": INPUT_LAYOUT, "output": OUTPUT_LAYOUT,
        "precision": cfg.runs.model_artifact,
        "backbone": getattr(net.model, "backbone_kind", None),
        # what the network scales its inputs with ([0, 1] units, RGB): the training frames' or the weights' own
        "image_mean": [float(v) for v in net.image_mean.flatten().cpu()],
        "image_std": [float(v) for v in net.image_std.flatten().cpu()],
        "standardized": bool(net.standardized),
        "label_mean": [float(v) for v in net.label_mean.cpu()], "label_std": [float(v) for v in net.label_std.cpu()],
        "train_mean": [float(v) for v in data.label_mean],  # the training-mean reference's relative pose
        "eval_thresholds": dataclasses.asdict(evaluate.thresholds(cfg.eval)),  # CTF/RPE settings of its traj.* metrics
        "run_id": run_id, "cell_key": cell.key, "cell": cell.label, "dataset_fingerprint": data.fingerprint,
        "bronchocli_version": __version__,
    }


def signature() -> ModelSignature:
    """Any frame size is accepted (a mismatch is resized with a warning, not refused by MLflow's schema check)."""
    return ModelSignature(inputs=Schema([TensorSpec(np.dtype(np.uint8), (-1, -1, -1, 3))]),
                          outputs=Schema([TensorSpec(np.dtype(np.float64), (-1, 6))]))


def input_example(data: RunData) -> np.ndarray:
    """The first two frames of the first test trajectory, ``[2, H, W, 3]`` (a real input, small)."""
    first = data.split.test[0] if data.split.test else data.split.train[0]
    return np.ascontiguousarray(data.cache.take(np.asarray(first.frame_index[:2])).transpose(0, 2, 3, 1))


def requirements() -> list[str]:
    """What loading imports: MLflow, and what the bundle's code imports (torch, numpy; Pillow to resize)."""
    return [f"mlflow=={mlflow.__version__}", f"torch=={torch.__version__.split('+')[0]}",
            f"numpy=={np.__version__}", f"pillow=={PIL.__version__}"]


def save_model_dir(path: Path, spec: dict[str, Any], weights: dict[str, Any], example: np.ndarray,
                   mlflow_model: Model | None = None) -> Path:
    """Write the MLflow model folder ``path`` (must not exist): MLmodel, code/, data/, example, environment."""
    code = bundle.bundle_for(spec["arch"])
    if code.problems:  # tests/training/test_bundle.py keeps the registered architectures free of these
        log.warning("the %s model's code is not self-contained (%s): loading it needs bronchocli installed",
                    spec["arch"], "; ".join(code.problems))
    with tempfile.TemporaryDirectory(prefix="bronchopose-model-") as tmp:
        data = Path(tmp) / DATA_DIR
        data.mkdir()
        torch.save(weights, data / WEIGHTS_FILE)
        (data / SPEC_FILE).write_text(json.dumps(spec, indent=2))
        package = bundle.write(code, Path(tmp) / "code")
        mlflow.pyfunc.save_model(
            str(path), loader_module=code.loader_module, data_path=str(data), code_paths=[str(package)],
            mlflow_model=mlflow_model, signature=signature(), input_example=example, pip_requirements=requirements(),
            metadata={"bronchopose": {k: spec[k] for k in ("arch", "image_size", "pose_frame", "input", "output")},
                      "requires": "torch and mlflow (the model's code is in code/)"},
        )
    _compact_json(path / "serving_input_example.json")
    return path


def _compact_json(path: Path) -> None:
    """MLflow indents the serving example one number per line (8 MB for two 256 px frames): rewrite it compact."""
    if path.is_file():
        path.write_text(json.dumps(json.loads(path.read_text()), separators=(",", ":")))


def model_tags(cfg: Config, cell: Cell, outcome: Outcome, precision: str, init: str | None = None) -> dict[str, str]:
    """The logged model's tags: which cell it is (``cell``: its label; the description, ``mlflow.note.content``,
    the run's, which the model's page shows) besides its coordinates. Its name stays ``MODEL_NAME``: MLflow 3
    resolves ``runs:/<run_id>/<name>`` by the logged model's name, so a model named after its cell would break
    ``runs:/<run_id>/model``; the Models tab's "Source run" column shows the run's name (the model's name and
    seed), and ``MODEL_NAME_TAG`` holds the model's name (``registry.model_name``)."""
    backbone = backbone_of(cfg)
    return {"cell": cell.label, TAG_NOTE: describe(cell, outcome.metrics, cfg.paths.dataset.name, backbone, init),
            MODEL_NAME_TAG: registry.model_name(cell.arch, cell.rot_loss, backbone, init),
            "arch": cell.arch, "pose_frame": cell.pose_frame, "cell_key": cell.key, "precision": precision}


def log_model(client, run_id: str, cfg: Config, cell: Cell, data: RunData, outcome: Outcome) -> str:
    """Log the run's MLflow Model (see the module doc); returns its logged-model id."""
    precision = cfg.runs.model_artifact
    spec = model_spec(cfg, cell, data, outcome, run_id)
    weights = export(outcome.network, cell, data.image_size, precision)
    run = client.get_run(run_id)  # its params as logged: the cell's, and the speed setting it trained with
    logged = client.create_logged_model(
        run.info.experiment_id, name=MODEL_NAME, source_run_id=run_id, model_type="bronchopose-pose",
        params=redacted(run.data.params),
        tags=model_tags(cfg, cell, outcome, precision, run.data.tags.get(TAG_INIT)))
    try:
        client.log_outputs(run_id, [LoggedModelOutput(logged.model_id, step=0)])
        meta = Model(artifact_path=logged.artifact_location, model_uuid=logged.model_id, run_id=run_id,
                     model_id=logged.model_id)
        with tempfile.TemporaryDirectory(prefix="bronchopose-") as tmp:
            local = save_model_dir(Path(tmp) / MODEL_NAME, spec, weights, input_example(data), meta)
            client.log_model_artifacts(logged.model_id, str(local))
    except BaseException:
        try:
            client.finalize_logged_model(logged.model_id, "FAILED")
        except Exception as exc:  # noqa: BLE001 - a full store: the run's failure path marks it (the original error
            log.warning("logged model %s not marked FAILED yet (%s)", logged.model_id,  # is the one to report)
                        str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        raise
    client.finalize_logged_model(logged.model_id, "READY")
    return logged.model_id
