"""What a trained model needs to predict, and nothing else: the code every logged MLflow Model carries.

A run's MLflow Model (``training/model_logging.py``) ships this module, byte for
byte, with the model modules it needs (``base.py``, ``backbones.py`` and the
architecture's own file) under ``code/bronchopose_model_<hash>/``, and names
this module as its pyfunc ``loader_module``. So ``mlflow.pyfunc.load_model``
works in a Python holding only torch and MLflow (numpy, and Pillow when frames
must be resized, come with MLflow): no bronchocli. That is why this module and
those it ships with import only the standard library, numpy, torch and each
other (relative imports); tests/training/test_bundle.py checks it for every
architecture. The project itself uses the same classes (one copy of each):
``training.network.PoseRegressor`` is :class:`Regressor` with the loss, and
``inference.mlflow_model.PoseModel`` is :class:`Predictor` with the run's
trajectory settings.

Input: uint8 frames ``[T, H, W, 3]`` (RGB, channel last, one video in time
order, T >= 2); output: ``float64 [T-1, 6]`` relative poses in the run's pose
frame (voxels, degrees). Frames whose size differs from the network's input
are resized with Pillow's bilinear filter (what the frame cache does when
``data.image_size`` differs from the dataset's) and one warning says so.
Runs on the CPU.
"""

from __future__ import annotations

import importlib
import json
import logging
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

log = logging.getLogger(__name__)

SPEC_FILE = "spec.json"  # in the model's data/bronchopose/ folder: what prediction needs besides the weights
WEIGHTS_FILE = "weights.pt"  # the network's state dict (fp16 or fp32), torch.load(weights_only=True)


class FrameSizeWarning(UserWarning):
    """Frames were resized to the network's input size."""


class InputError(ValueError):
    """Frames the model cannot take (wrong rank, channels, dtype, fewer than two)."""


def _buffer(values: Sequence[float], shape: tuple[int, ...]) -> torch.Tensor:
    return torch.tensor([float(v) for v in values], dtype=torch.float32).view(*shape)


class Regressor(nn.Module):
    """A pose network with its input normalisation and label standardisation (every statistic a buffer).

    Takes uint8 frames ``[B, T, 3, H, W]``, normalises them with the training frames' channel mean/std, runs
    the architecture and maps its output ``z`` to relative poses ``mu + sigma * z`` (the training labels'
    per-component mean and std; identity without ``standardized``), so a saved state dict predicts in
    physical units on its own.
    """

    def __init__(self, model: nn.Module, image_mean: Sequence[float], image_std: Sequence[float],
                 label_mean: Sequence[float] = (0.0,) * 6, label_std: Sequence[float] = (1.0,) * 6,
                 standardized: bool = False) -> None:
        super().__init__()
        self.model = model
        self.standardized = standardized
        self.register_buffer("image_mean", _buffer(image_mean, (1, 1, 3, 1, 1)))
        self.register_buffer("image_std", _buffer(image_std, (1, 1, 3, 1, 1)))
        self.register_buffer("label_mean", _buffer(label_mean, (6,)))
        self.register_buffer("label_std", _buffer(label_std, (6,)))

    @property
    def temporal(self) -> bool:
        return self.model.temporal

    def forward(self, frames: torch.Tensor, state: Any = None) -> tuple[torch.Tensor, Any]:
        if getattr(self.model, "prefix_cached", 0):  # features of the frozen stages, computed from normalised frames
            x = frames
        else:
            x = (frames.float().div_(255.0) - self.image_mean) / self.image_std
        z, state = self.model(x, state)
        return z.float() * self.label_std + self.label_mean, state


def restore(net: Regressor, state_dict: dict[str, torch.Tensor]) -> Regressor:
    """``net`` with a stored state dict (fp16 or fp32 values) loaded as fp32: on the CPU, eval mode."""
    net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state_dict.items()})
    return net.eval()


def check_frames(frames: Any, what: str = "frames", error: type[Exception] = InputError) -> np.ndarray:
    """``frames`` as a uint8 ``[T, H, W, 3]`` array, or ``error`` naming what is wrong."""
    arr = np.asarray(frames)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise error(f"{what}: expected uint8 frames [T, H, W, 3] (RGB, channel last), got shape {list(arr.shape)}")
    if arr.dtype != np.uint8:
        raise error(f"{what}: expected uint8 pixels (0-255), got {arr.dtype}")
    if len(arr) < 2:
        raise error(f"{what}: {len(arr)} frame(s); a relative pose needs at least 2")
    return arr


def resize_frame(frame: np.ndarray, size: int) -> np.ndarray:
    """One ``[H, W, 3]`` uint8 frame -> ``[size, size, 3]``, bilinear (the frame cache's resize)."""
    if frame.shape[:2] == (size, size):
        return frame
    from PIL import Image  # lazy: only frames of another size need Pillow (MLflow installs it)

    return np.asarray(Image.fromarray(frame).resize((size, size), Image.Resampling.BILINEAR))


def warn_resize(shape: tuple[int, ...], size: int, what: str = "frames") -> None:
    h, w = shape[:2]
    message = (f"{what} are {w}x{h} pixels, the network takes {size}x{size}: resizing them (bilinear), as "
               f"training resized its frames; results are only as good as the match between the two")
    warnings.warn(message, FrameSizeWarning, stacklevel=3)
    log.warning(message)


class Predictor:
    """A trained run's network with what prediction needs (``spec``): the pyfunc's model implementation."""

    input_error: type[Exception] = InputError  # what bad frames raise (the project raises its one-line kind)

    def __init__(self, net: Regressor, spec: dict[str, Any]) -> None:
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
            raise self.input_error(f"{len(clip)} frame(s); a relative pose needs at least 2")
        if on_frames is not None and fed:
            on_frames(fed)
        return torch.cat(outputs).numpy()

    def _forward(self, clip: list[np.ndarray], state: Any, outputs: list[torch.Tensor]) -> Any:
        out, state = self.net(self._tensor(clip).unsqueeze(0), state)
        outputs.append(out[0].double())
        return state

    def get_raw_model(self) -> Predictor:
        """What ``PyFuncModel.get_raw_model()`` returns: this object (``.net``: the torch module, ``.spec``: JSON)."""
        return self

    def predict(self, model_input: Any, params: dict[str, Any] | None = None) -> np.ndarray:
        """pyfunc entry point: uint8 ``[T, H, W, 3]`` -> ``float64 [T-1, 6]`` (see the module doc)."""
        if isinstance(model_input, dict) and len(model_input) == 1:  # a named tensor
            model_input = next(iter(model_input.values()))
        if hasattr(model_input, "to_numpy") and not isinstance(model_input, np.ndarray):  # a one-column DataFrame
            model_input = np.stack(model_input.iloc[:, 0].to_list())
        frames = check_frames(model_input, error=self.input_error)
        if frames.shape[1:3] != (self.image_size, self.image_size):
            warn_resize(frames.shape[1:3], self.image_size)
        return self.relative_poses(frames)


def model_class(path: str) -> Callable[..., nn.Module]:
    """``".baseline:BaselineNet"`` (a module shipped beside this one) or ``"package.module:Class"`` -> the class."""
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module, __package__), attr)


def load(data_dir: str | Path) -> Predictor:
    """The model in an MLflow model's ``data/bronchopose/`` folder, built from the classes shipped with it."""
    data_dir = Path(data_dir)
    spec = json.loads((data_dir / SPEC_FILE).read_text(encoding="utf-8"))
    payload = torch.load(data_dir / WEIGHTS_FILE, map_location="cpu", weights_only=True)
    backbone = spec.get("backbone")  # absent in specs written before model.backbone, and for OffsetNet's
    extra = {"backbone": backbone} if backbone not in (None, "efficientnet_b0", "resnet34") else {}
    model = model_class(spec["model_class"])(image_size=int(spec["image_size"]), **extra)
    net = Regressor(model, (0.0,) * 3, (1.0,) * 3, standardized=bool(spec["standardized"]))
    return Predictor(restore(net, payload["state_dict"]), spec)


def _load_pyfunc(data_path: str) -> Predictor:
    """MLflow's ``python_function`` loader hook (the MLmodel names this module as ``loader_module``)."""
    return load(data_path)
