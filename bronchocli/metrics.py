"""Losses and metrics on poses: per image pair and accumulated over trajectories.

All functions take pose 6-vectors ``(..., 6)`` = (x, y, z, alpha, beta, gamma),
positions in voxels and XYZ Euler angles in degrees (geometry.py), and return
one value per pose ``(...)``. They are differentiable torch code, so the same
function is a training loss (after ``.mean()``) and an evaluation metric.

* ``pos_mse``  mean squared position error (voxels^2), ``pos_l2`` its norm (voxels),
  ``pos_l2_mm`` the same in mm (the dataset's voxel spacing);
* ``rot_mse``  mean squared wrapped angle error (deg^2), ``rot_l2`` its norm (deg);
* ``de``       direction error arccos(v_E . v_GT), v = R (1,0,0), radians.  DE
  only sees where the optical axis points, so it is blind to a roll about that
  axis; CE and the geodesic angle are not;
* ``ce``       cosine error mean_i (1 - cos(theta_E,i - theta_GT,i)), the
  angles converted to radians first (the authors' code fed degrees to cos);
* ``geodesic`` angle of R_E^T R_GT in degrees.

Which of them are metrics and rotation losses, under which names, units, labels
and directions, is registry.py's (``register_metric``, ``register_rot_loss``):
this module holds the functions and applies every registered per-pose metric.

Rotation L2 and CE compare Euler triples angle by angle, which only compares
rotations when both triples are in the same (canonical) form: wherever a
triple stands for a rotation (an absolute orientation, a ``camera``-frame
relative pose), :func:`per_pose_errors` with ``rotations=True`` first rewrites
both in the canonical form (geometry.canonical_euler), so the error does not
depend on which of the two XYZ triples of a rotation was written. ``world``-frame
relative poses are angle differences, not rotations, and are compared as they are.

The arccos inside ``de`` and ``geodesic`` clamps its argument, so it never
returns NaN; as a loss it clamps slightly inside [-1, 1] so the gradient is
finite at zero error (arccos' derivative is infinite at 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np
import torch

from . import geometry, registry

_LOSS_CLAMP = 1e-6  # keeps arccos' gradient finite when used as a loss


def _pos_err(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    return pred[..., :3] - gt[..., :3]


def _rot_err(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Wrapped angle differences in degrees, ``(..., 3)``."""
    return geometry.wrap_deg(pred[..., 3:] - gt[..., 3:])


def _safe_norm(x: torch.Tensor) -> torch.Tensor:
    # sqrt has an infinite derivative at 0: add a tiny epsilon under the root
    # only where the gradient is needed, so metric values stay exact.
    sq = (x * x).sum(-1)
    if sq.requires_grad:
        return torch.sqrt(sq + 1e-12)
    return torch.sqrt(sq)


def _safe_acos(x: torch.Tensor) -> torch.Tensor:
    lim = 1.0 - _LOSS_CLAMP if x.requires_grad else 1.0
    return torch.arccos(x.clamp(-lim, lim))


def pos_mse(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    return (_pos_err(pred, gt) ** 2).mean(-1)


def pos_l2(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Position L2: the Euclidean norm of the predicted minus the true position change (x, y, z), in voxels."""
    return _safe_norm(_pos_err(pred, gt))


def rot_mse(pred: torch.Tensor, gt: torch.Tensor, scale: torch.Tensor | None = None) -> torch.Tensor:
    """``scale`` (3,): divide each angle error by it first (the training labels' std: pose_loss)."""
    err = _rot_err(pred, gt)
    return ((err if scale is None else err / scale) ** 2).mean(-1)


def rot_l2(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Rotation L2: the Euclidean norm of the predicted minus the true Euler angles (each difference wrapped into
    (-180°, 180°]), in degrees."""
    return _safe_norm(_rot_err(pred, gt))


def pos_l2_mm(pred: torch.Tensor, gt: torch.Tensor, spacing_mm: torch.Tensor) -> torch.Tensor:
    """Position L2 in mm: the error's voxel axes scaled by the voxel spacing ``(..., 3)`` first."""
    return torch.linalg.vector_norm(_pos_err(pred, gt) * spacing_mm, dim=-1)


def direction_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """DE: the angle arccos(v_E · v_GT) between the predicted and the true viewing direction, v = R·(1, 0, 0) the
    camera's forward axis (the cosine clamped to [-1, 1]), in radians."""
    v_pred = geometry.forward_vector(pred[..., 3:])
    v_gt = geometry.forward_vector(gt[..., 3:])
    return _safe_acos((v_pred * v_gt).sum(-1))


def cosine_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """CE: the mean over the three Euler angles of 1 − cos(predicted − true angle), unitless (0 = exact)."""
    return (1.0 - torch.cos(torch.deg2rad(pred[..., 3:] - gt[..., 3:]))).mean(-1)


def geodesic(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    R_pred = geometry.euler_to_matrix(pred[..., 3:])
    R_gt = geometry.euler_to_matrix(gt[..., 3:])
    trace = (R_pred * R_gt).sum((-1, -2))  # trace(R_pred^T R_gt)
    return torch.rad2deg(_safe_acos((trace - 1.0) / 2.0))


def metric_functions() -> dict[str, Callable[..., torch.Tensor]]:
    """Every registered per-pose metric (registry.metric_specs): name -> its function, in registration order."""
    return {spec.name: registry.resolve(spec, globals()) for spec in registry.metric_specs(per="pose")}


def pose_loss(pred: torch.Tensor, gt: torch.Tensor, rot_loss: str, rot_weight: float = 1.0,
              scale: torch.Tensor | None = None, rot_scale: bool = False) -> torch.Tensor:
    """Training loss L_pos(MSE) + w * L_rot, averaged over every pose in the batch.

    ``rot_loss``: a registered rotation loss (registry.register_rot_loss). ``scale`` (6,): divide the
    position errors, and the rotation errors of a ``scaled`` rotation loss (MSE), by these (the training
    labels' std when labels are standardised), so each component weighs the same whatever its unit.
    ``rot_scale`` (train.rot_scale: label_std): with ``scale``, a bounded angular loss (DE, CE) is divided by
    its own value at an error of one label std in every angle (:func:`rot_loss_unit`), as MSE's squared errors
    are; without it they enter as the paper writes them (on the default dataset CE ~1/100 and DE ~1/9 of one
    std's position term: benchmarks/bench_rot_units.py).
    """
    try:
        spec = registry.rot_loss(rot_loss)
    except KeyError:
        raise ValueError(f"rotation loss {rot_loss!r} is not one of {', '.join(registry.rot_loss_names())}"
                         ) from None
    rot = registry.resolve(spec, globals())
    if scale is None:
        return pos_mse(pred, gt).mean() + rot_weight * rot(pred, gt).mean()
    pos = ((_pos_err(pred, gt) / scale[:3]) ** 2).mean(-1)
    if spec.scaled:
        rot_term = rot(pred, gt, scale=scale[3:])
    elif rot_scale:
        rot_term = rot(pred, gt) / rot_loss_unit(rot, scale)
    else:
        rot_term = rot(pred, gt)
    return pos.mean() + rot_weight * rot_term.mean()


def rot_loss_unit(rot: Callable[..., torch.Tensor], scale: torch.Tensor) -> torch.Tensor:
    """A rotation loss's value at an error of one label std ``scale[3:]`` in every angle (from no rotation): the
    unit that puts a bounded loss on the scale of standardised MSE (1 at one std; ``pose_loss``)."""
    err = torch.zeros(6, dtype=scale.dtype, device=scale.device)
    err[3:] = scale[3:]
    return rot(err, torch.zeros_like(err)).clamp_min(torch.finfo(scale.dtype).tiny)


@dataclass(frozen=True)
class Stat:
    """Mean and population standard deviation (ddof=0) over ``n`` values."""

    mean: float
    std: float
    n: int

    @classmethod
    def of(cls, values: np.ndarray) -> "Stat":
        values = np.asarray(values, dtype=np.float64).ravel()
        if values.size == 0:
            return cls(math.nan, math.nan, 0)
        return cls(float(values.mean()), float(values.std(ddof=0)), int(values.size))


def _to_tensor(x) -> torch.Tensor:
    return torch.from_numpy(np.array(x, dtype=np.float64))  # a copy: inputs may be read-only views


def per_pose_errors(pred, gt, spacing_mm: Sequence[float] | None = None, *,
                    rotations: bool = False) -> dict[str, np.ndarray]:
    """Every registered per-pose metric for each pose of ``pred``/``gt`` ``(N, 6)``, as float64 arrays of length N
    (the ``spacing`` ones, in mm, only with ``spacing_mm``).

    ``rotations``: the angle triples stand for rotations (absolute poses, ``camera``-frame deltas); both are
    made canonical first, so rotation L2 and CE compare rotations, not whichever triple was written.
    """
    p, g = _to_tensor(pred).reshape(-1, 6), _to_tensor(gt).reshape(-1, 6)
    if rotations:
        p, g = geometry.canonical_pose(p), geometry.canonical_pose(g)
    scale = None if spacing_mm is None else _to_tensor(spacing_mm)
    out = {}
    with torch.no_grad():
        for spec in registry.metric_specs(per="pose"):
            fn = registry.resolve(spec, globals())
            if not spec.spacing:
                out[spec.name] = fn(p, g).numpy()
            elif scale is not None:  # a metric in mm: only where the voxel spacing is known
                out[spec.name] = fn(p, g, scale).numpy()
    return out


def pair_metrics(pred, gt, spacing_mm: Sequence[float] | None = None, *, rotations: bool = False
                 ) -> dict[str, Stat]:
    """Per image pair: metrics of predicted vs true relative poses ``(N, 6)``, mean and std over pairs
    (``rotations``: see :func:`per_pose_errors`; True for ``camera``-frame deltas and absolute poses)."""
    return {k: Stat.of(v) for k, v in per_pose_errors(pred, gt, spacing_mm, rotations=rotations).items()}


def accumulated_endpoints(
    trajectories: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], frame: geometry.PoseFrame
) -> tuple[np.ndarray, np.ndarray]:
    """Chain each trajectory's predicted and true relative poses from its first pose.

    ``trajectories`` yields ``(start (6,), pred_deltas (N, 6), gt_deltas (N, 6))``;
    returns the predicted and true final poses, ``(n_trajectories, 6)`` each.
    """
    ends_pred, ends_gt = [], []
    for start, pred, gt in trajectories:
        ends_pred.append(geometry.accumulate(start, pred, frame)[-1])
        ends_gt.append(geometry.accumulate(start, gt, frame)[-1])
    return np.asarray(ends_pred).reshape(-1, 6), np.asarray(ends_gt).reshape(-1, 6)


def accumulated_metrics(
    trajectories: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
    frame: geometry.PoseFrame,
    spacing_mm: Sequence[float] | None = None,
) -> dict[str, Stat]:
    """Accumulated evaluation: chain whole trajectories, score the last pose only; stats over trajectories.
    The endpoints are orientations, compared as rotations whatever form either triple is written in."""
    pred_end, gt_end = accumulated_endpoints(trajectories, frame)
    return pair_metrics(pred_end, gt_end, spacing_mm, rotations=True)
