"""The loader of the MLflow Model every FINISHED run logs (``training/model_logging.py`` writes it).

``mlflow.pyfunc.load_model("runs:/<run_id>/model")`` imports this module and
calls :func:`_load_pyfunc` on the model's ``data/bronchopose/`` folder; the returned
:class:`PoseModel` is what ``predict`` runs. Input: uint8 frames
``[T, H, W, 3]`` (RGB, channel last, one video in time order, T >= 2);
output: ``float64 [T-1, 6]`` relative poses in the run's pose frame
(voxels, degrees). Frames whose size differs from the network's input are
resized with Pillow's bilinear filter (what the frame cache does when
``data.image_size`` differs from the dataset's) and one warning says so.
Runs on the CPU; no VTK.
"""

from __future__ import annotations

import json
import logging
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from ..errors import BronchoError
from ..odometry import Thresholds
from ..training import checkpoint
from ..training.model_logging import SPEC_FILE, SPEC_FORMAT, SPEC_VERSION, WEIGHTS_FILE
from ..training.network import PoseRegressor, load_exported

log = logging.getLogger(__name__)


class FrameSizeWarning(UserWarning):
    """Frames were resized to the network's input size."""


class ModelInputError(BronchoError, ValueError):
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
    arr = np.asarray(frames)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise ModelInputError(f"{what}: expected uint8 frames [T, H, W, 3] (RGB, channel last), got shape "
                              f"{list(arr.shape)}")
    if arr.dtype != np.uint8:
        raise ModelInputError(f"{what}: expected uint8 pixels (0-255), got {arr.dtype}")
    if len(arr) < 2:
        raise ModelInputError(f"{what}: {len(arr)} frame(s); a relative pose needs at least 2")
    return arr


def resize_frame(frame: np.ndarray, size: int) -> np.ndarray:
    """One ``[H, W, 3]`` uint8 frame -> ``[size, size, 3]``, bilinear (the frame cache's resize)."""
    if frame.shape[:2] == (size, size):
        return frame
    return np.asarray(Image.fromarray(frame).resize((size, size), Image.Resampling.BILINEAR))


def warn_resize(shape: tuple[int, ...], size: int, what: str = "frames") -> None:
    h, w = shape[:2]
    message = (f"{what} are {w}x{h} pixels, the network takes {size}x{size}: resizing them (bilinear), as "
               f"training resized its frames; results are only as good as the match between the two")
    warnings.warn(message, FrameSizeWarning, stacklevel=3)
    log.warning(message)


class PoseModel:
    """A trained run's network with what prediction needs (``spec``): the pyfunc's model implementation."""

    def __init__(self, net: PoseRegressor, spec: dict[str, Any]) -> None:
        self.net, self.spec = net.eval(), spec

    @property
    def image_size(self) -> int:
        return int(self.spec["image_size"])

    @property
    def pose_frame(self) -> str:
        return str(self.spec["pose_frame"])

    @property
    def chunk(self) -> int:
        return int(self.spec["chunk"])

    @property
    def thresholds(self) -> Thresholds:
        """The run's ``eval:`` settings of its trajectory metrics (CTF, RPE); the defaults for older models."""
        return Thresholds(**self.spec.get("eval_thresholds", {}))

    @property
    def train_mean(self) -> np.ndarray:
        return np.asarray(self.spec["train_mean"], dtype=np.float64)

    def _tensor(self, frames: Iterable[np.ndarray]) -> torch.Tensor:
        return torch.from_numpy(np.stack([resize_frame(f, self.image_size) for f in frames]).transpose(0, 3, 1, 2))

    @torch.no_grad()
    def relative_poses(self, frames: Iterable[np.ndarray], on_frames: Callable[[int], None] | None = None
                       ) -> np.ndarray:
        """Relative poses ``(n-1, 6)`` of a stream of ``[H, W, 3]`` uint8 frames, read chunk by chunk.

        The same chunks as evaluation (``chunk`` pairs per forward, overlapping by one frame, a recurrent
        state carried through), so a test trajectory gives the run's logged predictions.
        ``on_frames(k)`` is told after each chunk how many new frames it consumed.
        """
        outputs: list[torch.Tensor] = []
        state, clip, fed = None, [], 0
        for frame in frames:
            clip.append(frame)
            fed += 1
            if len(clip) == self.chunk + 1:
                state = self._forward(clip, state, outputs)
                clip = clip[-1:]
                if on_frames is not None:
                    on_frames(fed)
                    fed = 0
        if len(clip) > 1:
            self._forward(clip, state, outputs)
        if not outputs:
            raise ModelInputError(f"{len(clip)} frame(s); a relative pose needs at least 2")
        if on_frames is not None and fed:
            on_frames(fed)
        return torch.cat(outputs).numpy()

    def _forward(self, clip: list[np.ndarray], state, outputs: list[torch.Tensor]):
        out, state = self.net(self._tensor(clip).unsqueeze(0), state)
        outputs.append(out[0].double())
        return state

    def get_raw_model(self) -> PoseModel:
        """What ``PyFuncModel.get_raw_model()`` returns: this object (``.net`` is the torch module, ``.spec`` the JSON)."""
        return self

    def predict(self, model_input: Any, params: dict[str, Any] | None = None) -> np.ndarray:
        """pyfunc entry point: uint8 ``[T, H, W, 3]`` -> ``float64 [T-1, 6]`` (see the module doc)."""
        if isinstance(model_input, dict) and len(model_input) == 1:  # a named tensor
            model_input = next(iter(model_input.values()))
        if hasattr(model_input, "to_numpy") and not isinstance(model_input, np.ndarray):  # a one-column DataFrame
            model_input = np.stack(model_input.iloc[:, 0].to_list())
        frames = check_frames(model_input)
        if frames.shape[1:3] != (self.image_size, self.image_size):
            warn_resize(frames.shape[1:3], self.image_size)
        return self.relative_poses(frames)


def load_data_dir(data_dir: str | Path) -> PoseModel:
    """The model in an MLflow model's ``data/`` folder (weights + spec), on the CPU, fp32, eval mode."""
    data_dir = Path(data_dir)
    spec = read_spec(data_dir)
    payload = checkpoint.read_plain(data_dir / WEIGHTS_FILE, "model weights file",
                                    "re-download the model or retrain its run")
    return PoseModel(load_exported(payload), spec)


def _load_pyfunc(data_path: str) -> PoseModel:
    """MLflow's ``python_function`` loader hook (the MLmodel names this module as ``loader_module``)."""
    return load_data_dir(data_path)
