"""The inference half of the public API: load a trained run's model, predict relative poses, chain them, score them.

* :func:`load_model` -- a run's MLflow Model by run id, ``models:/<name>/<version>``,
  ``models:/<name>@<alias>``, ``models:/<model_id>``, ``runs:/<id>/model`` or a local folder;
* :func:`read_frames` / :func:`read_poses` -- uint8 frames ``[T, H, W, 3]`` of a folder, a video or a dataset
  trajectory, and ground-truth poses ``[T, 6]`` of a dataset trajectory or a pose CSV;
* :func:`predict` -- the ``T-1`` relative poses of ``T`` frames, in the model's pose frame;
* :func:`chain` -- relative poses -> absolute trajectory ``[T, 6]`` from a first pose;
* :func:`score` -- per-pair and accumulated errors of a prediction and of both image-blind references.

Poses follow the project's convention (docs/conventions.md): position in
voxels, orientation as intrinsic XYZ Euler angles in degrees.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from mlflow.tracking import MlflowClient

from .. import geometry
from ..config import DEFAULT_CONFIG, load_config
from ..config.arguments import ArgumentError
from ..inference import loading, reader, trajectory
from ..inference.mlflow_model import PoseModel, check_frames, warn_resize
from ..runs.client import client_for, require_store


def load_model(reference: str, *, mlflow_uri: str | None = None,
               config: str | os.PathLike = DEFAULT_CONFIG) -> PoseModel:
    """The model of ``reference`` on the CPU (fp32 compute, eval mode).

    The MLflow store is ``mlflow_uri`` when given, else the one of ``config``
    (``experiments.yaml`` by default). A local model folder needs neither.
    """
    if mlflow_uri is not None:
        client = MlflowClient(tracking_uri=mlflow_uri)
    elif (Path(reference).expanduser() / "MLmodel").is_file():
        return loading.load_local(Path(reference).expanduser())
    else:
        cfg = load_config(config)
        require_store(cfg)  # a mistyped runs.uri: one line, no empty store created
        client = client_for(cfg)
    return loading.load(client, reference).model


def read_frames(path: str | os.PathLike) -> np.ndarray:
    """uint8 frames ``[T, H, W, 3]`` (RGB) of a folder of images, a video file or
    ``<dataset root>/<patient>/<lobe>/<trajectory>``."""
    inp = reader.open_input(path)
    return np.stack(list(inp.frames()))


def read_poses(path: str | os.PathLike) -> np.ndarray:
    """Ground-truth absolute poses ``[T, 6]`` of ``<dataset root>/<patient>/<lobe>/<trajectory>`` or a pose CSV
    (dataset CSV columns ``pos_x pos_y pos_z Rx Ry Rz``, as ``bronchopose track`` writes them)."""
    return reader.read_ground_truth(path).poses.copy()


def predict(model: PoseModel, frames: np.ndarray) -> np.ndarray:
    """Relative poses ``float64 [T-1, 6]`` of uint8 frames ``[T, H, W, 3]`` in ``model.pose_frame``.

    Frames of another size than ``model.image_size`` are resized (bilinear) with a ``FrameSizeWarning``.
    """
    frames = check_frames(frames)
    if frames.shape[1:3] != (model.image_size, model.image_size):
        warn_resize(frames.shape[1:3], model.image_size)
    return model.relative_poses(frames)


def chain(model: PoseModel, relative: np.ndarray, first_pose: np.ndarray | None = None) -> np.ndarray:
    """Absolute poses ``[T, 6]``: ``relative`` chained from ``first_pose`` (default: all zeros) in the model's
    pose frame (summed in ``world``, composed in ``camera``)."""
    start = np.zeros(6) if first_pose is None else _poses("api.chain", "first_pose", first_pose, 1)
    return geometry.accumulate(start, _poses("api.chain", "relative", relative, 2), model.pose_frame)


def _poses(call: str, name: str, value: object, ndim: int) -> np.ndarray:
    """``value`` as float64 poses (``[6]`` or ``[T, 6]``), else one ArgumentError naming the argument."""
    want = "[6]" if ndim == 1 else "[T, 6]"
    if isinstance(value, (str, bytes)):
        raise ArgumentError(f"{call}: {name}: must be an array of numbers {want}, not a string")
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ArgumentError(f"{call}: {name}: must be an array of numbers {want}") from None
    if array.ndim != ndim or array.shape[-1] != 6:
        raise ArgumentError(f"{call}: {name}: shape {tuple(array.shape)}: must be {want}")
    if not np.isfinite(array).all():
        raise ArgumentError(f"{call}: {name}: not finite (NaN or infinity)")
    return array


def score(model: PoseModel, relative: np.ndarray, ground_truth: np.ndarray,
          spacing_mm: tuple[float, float, float] | None = None) -> dict[str, float]:
    """Errors of one predicted trajectory against ``ground_truth`` ``[T, 6]``, as the run's evaluation computes them.

    Keys ``<source>.<pair|acc>.<metric>``: ``source`` is ``model``, ``zero_motion`` or ``train_mean`` (the
    image-blind references, the latter the run's training-mean relative pose); ``pair`` is the mean over the
    ``T-1`` pairs, ``acc`` the endpoint error after chaining from the true first pose; ``metric`` is one of
    ``pos_l2`` (voxels), ``pos_l2_mm`` (NaN without ``spacing_mm``), ``rot_l2`` (degrees), ``de`` (radians),
    ``ce``, ``geodesic`` (degrees); plus ``<source>.traj.<t>`` trajectory metrics (CTF, ATE, RPE, drift) with
    the run's ``eval:`` thresholds.
    """
    gt = np.asarray(ground_truth, dtype=np.float64)
    spacing = np.full(3, np.nan) if spacing_mm is None else np.asarray(spacing_mm, dtype=np.float64)
    if len(gt) != len(relative) + 1:
        raise ValueError(f"ground truth has {len(gt)} poses for {len(relative)} relative poses; need one more")
    row = trajectory.score(model, relative, reader.GroundTruth(gt, spacing)).iloc[0]
    return {k: float(v) for k, v in row.items() if "." in str(k)}
