"""The project's side of a run's MLflow Model (``training/model_logging.py`` writes it): read and predict.

A model's own pyfunc loader is ``models/portable.py``, shipped inside the model,
so ``mlflow.pyfunc.load_model("runs:/<run_id>/model")`` needs no bronchocli.
The project loads the same folder with its own classes (:func:`load_data_dir`):
:class:`PoseModel` is ``portable.Predictor`` (the same chunked prediction) plus
the run's trajectory settings, raising the project's one-line error kind.
Models logged before the bundle name *this* module as their loader
(``LEGACY_LOADER``): :func:`_load_pyfunc` keeps them loading where bronchocli is
installed. Input: uint8 frames ``[T, H, W, 3]`` (RGB, channel last, one video
in time order, T >= 2); output: ``float64 [T-1, 6]`` relative poses in the
run's pose frame (voxels, degrees). Runs on the CPU; no VTK.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import BronchoError
from ..models import portable
from ..models.portable import SPEC_FILE, WEIGHTS_FILE, FrameSizeWarning, resize_frame, warn_resize
from ..odometry import Thresholds
from ..training import checkpoint
from ..training.model_logging import SPEC_FORMAT, SPEC_VERSION
from ..training.network import load_exported

LEGACY_LOADER = __name__  # the loader_module of models logged before they carried their code

__all__ = ["FrameSizeWarning", "ModelInputError", "PoseModel", "check_frames", "load_data_dir", "read_spec",
           "resize_frame", "warn_resize"]


class ModelInputError(BronchoError, portable.InputError):
    """Frames the model cannot take (wrong rank, channels, dtype, fewer than two)."""


def read_spec(data_dir: Path) -> dict[str, Any]:
    path = Path(data_dir) / SPEC_FILE
    try:
        spec = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise BronchoError(f"{path}: not a bronchopose model description ({exc})") from None
    if spec.get("format") != SPEC_FORMAT or int(spec.get("version", 0)) > SPEC_VERSION:
        raise BronchoError(f"{path}: format {spec.get('format')!r} version {spec.get('version')!r} is not one this "
                           f"bronchocli reads ({SPEC_FORMAT} <= {SPEC_VERSION}); upgrade bronchocli")
    return spec


def check_frames(frames: np.ndarray, what: str = "frames") -> np.ndarray:
    """``frames`` as a uint8 ``[T, H, W, 3]`` array, or ModelInputError naming what is wrong."""
    return portable.check_frames(frames, what, ModelInputError)


class PoseModel(portable.Predictor):
    """A trained run's network with what prediction needs (``spec``), and the run's trajectory settings."""

    input_error = ModelInputError

    @property
    def thresholds(self) -> Thresholds:
        """The run's ``eval:`` settings of its trajectory metrics (CTF, RPE); the defaults for older models."""
        return Thresholds(**self.spec.get("eval_thresholds", {}))

    @property
    def train_mean(self) -> np.ndarray:
        return np.asarray(self.spec["train_mean"], dtype=np.float64)


def load_data_dir(data_dir: str | Path) -> PoseModel:
    """The model in an MLflow model's ``data/`` folder (weights + spec), on the CPU, fp32, eval mode."""
    data_dir = Path(data_dir)
    spec = read_spec(data_dir)
    payload = checkpoint.read_plain(data_dir / WEIGHTS_FILE, "model weights file",
                                    "re-download the model or retrain its run")
    return PoseModel(load_exported(payload), spec)


def _load_pyfunc(data_path: str) -> PoseModel:
    """MLflow's ``python_function`` loader hook of models logged before they carried their code."""
    return load_data_dir(data_path)
