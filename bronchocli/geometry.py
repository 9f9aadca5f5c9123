"""Pose conventions: Euler angles, rotation matrices, relative poses, accumulation.

The single source of truth for the pose conventions (docs/conventions.md):

* a pose is a 6-vector ``(x, y, z, alpha, beta, gamma)``: position in world
  voxels, orientation as intrinsic X-Y-Z Euler angles in degrees, i.e.
  ``R = Rx(alpha) @ Ry(beta) @ Rz(gamma)`` (SciPy ``from_euler("XYZ", ...)``);
* the camera frame is x forward (optical axis), y left, z up, so the columns
  of ``R`` are (forward, left, up);
* relative poses come in two parameterisations, ``world`` (the paper's plain
  differences, accumulated by summing) and ``camera`` (SE(3), expressed in the
  previous camera's frame, accumulated by composing).

Every function works on NumPy arrays and on torch tensors alike, batched over
any leading dimensions; torch is only imported when a tensor is passed in.
On NumPy arrays the trigonometry and matrix products are :mod:`.hostfree`'s, so
poses computed here (a dataset's, its labels) are the same bits on every host.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np

from . import hostfree as hf

PoseFrame = Literal["world", "camera"]
POSE_FRAMES: tuple[str, ...] = ("world", "camera")

# Below this, cos(beta) is treated as exactly zero (gimbal lock): alpha is set
# to 0 and gamma absorbs the whole rotation about the shared axis.
_GIMBAL_EPS = 1e-12


def _xp(x: Any):
    """The array namespace of ``x`` (numpy or torch)."""
    if type(x).__module__.startswith("torch"):
        import torch  # lazy: already loaded when a tensor is passed; numpy callers (generation) never load it

        return torch
    return np


def _cos(x):
    return hf.cos(x) if _xp(x) is np else x.cos()


def _sin(x):
    return hf.sin(x) if _xp(x) is np else x.sin()


def _atan2(y, x):
    return hf.atan2(y, x) if _xp(y) is np else _xp(y).arctan2(y, x)


def _matmul(a, b):
    """``a @ b``; on NumPy arrays without BLAS (whose kernel, and rounding, depends on the CPU)."""
    return hf.matmul(a, b) if _xp(a) is np else a @ b


def _as_array(x):
    """Tensors stay tensors; everything else becomes a float64 ndarray."""
    if _xp(x) is np:
        return np.asarray(x, dtype=np.float64)
    return x if x.is_floating_point() else x.double()


def wrap_deg(angles):
    """Wrap angles in degrees into (-180, 180]."""
    a = _as_array(angles)
    xp = _xp(a)
    return a - 360.0 * xp.ceil((a - 180.0) / 360.0)


def wrap_rad(angles):
    """Wrap angles in radians into (-pi, pi]."""
    a = _as_array(angles)
    xp = _xp(a)
    return a - 2.0 * math.pi * xp.ceil((a - math.pi) / (2.0 * math.pi))


def euler_to_matrix(angles_deg):
    """Intrinsic XYZ Euler angles in degrees ``(..., 3)`` -> rotation matrices ``(..., 3, 3)``."""
    e = _as_array(angles_deg)
    xp = _xp(e)
    rad = e * (math.pi / 180.0)
    ca, cb, cc = _cos(rad[..., 0]), _cos(rad[..., 1]), _cos(rad[..., 2])
    sa, sb, sc = _sin(rad[..., 0]), _sin(rad[..., 1]), _sin(rad[..., 2])
    rows = [
        [cb * cc, -cb * sc, sb],
        [ca * sc + sa * sb * cc, ca * cc - sa * sb * sc, -sa * cb],
        [sa * sc - ca * sb * cc, sa * cc + ca * sb * sc, ca * cb],
    ]
    return xp.stack([xp.stack(r, -1) for r in rows], -2)


def matrix_to_euler(R):
    """Rotation matrices ``(..., 3, 3)`` -> intrinsic XYZ Euler angles in degrees ``(..., 3)``.

    alpha is taken from the third column; beta and gamma are then read from
    ``Rx(alpha)^T R = Ry(beta) Rz(gamma)``, so an imprecise alpha near gimbal
    lock is compensated by gamma and ``euler_to_matrix`` reproduces ``R``.
    beta lies in [-90, 90] and alpha, gamma in (-180, 180], exactly (never -180, never 90 + 1 ulp); at gimbal
    lock alpha is 0.
    """
    R = _as_array(R)
    xp = _xp(R)
    r12, r22 = R[..., 1, 2], R[..., 2, 2]
    gimbal = xp.sqrt(r12 * r12 + r22 * r22) < _GIMBAL_EPS
    alpha = xp.where(gimbal, xp.zeros_like(r12), _atan2(-r12, r22))
    ca, sa = _cos(alpha), _sin(alpha)
    # Rows of Rx(alpha)^T R that hold beta and gamma (see the docstring).
    n02 = R[..., 0, 2]
    n22 = (-sa * R[..., 1, 2] + ca * R[..., 2, 2]).clip(min=0.0)  # = cos(beta) >= 0; rounding can make it -0.0
    n10 = ca * R[..., 1, 0] + sa * R[..., 2, 0]
    n11 = ca * R[..., 1, 1] + sa * R[..., 2, 1]
    beta = _atan2(n02, n22)
    gamma = _atan2(n10, n11)
    return _in_ranges(xp.stack([alpha, beta, gamma], -1) * (180.0 / math.pi))


def _in_ranges(e):
    """Euler triples (degrees) exactly inside the documented ranges: alpha, gamma in (-180, 180] (atan2 gives
    -180 for a -0.0 sine) and |beta| <= 90 (pi/2 in degrees rounds to 90 + 1 ulp)."""
    xp = _xp(e)
    a, b, c = e[..., 0], e[..., 1], e[..., 2]
    a = xp.where(a <= -180.0, a + 360.0, a).clip(max=180.0)
    c = xp.where(c <= -180.0, c + 360.0, c).clip(max=180.0)
    return xp.stack([a, b.clip(-90.0, 90.0), c], -1)


def canonical_euler(angles_deg):
    """The canonical XYZ triple of each rotation ``(..., 3)``: beta in [-90, 90], alpha and gamma in (-180, 180].

    Every rotation has two XYZ triples, (a, b, c) and (a+180, 180-b, c+180); this one is what
    :func:`matrix_to_euler` (and so chaining in the ``camera`` frame) returns. Comparing two triples angle by
    angle only compares rotations when both are canonical. A triple that already is canonical (|beta| < 90,
    alpha and gamma in (-180, 180]) is returned bit for bit; the others go through the matrix and back.
    """
    e = _as_array(angles_deg)
    xp = _xp(e)
    a, b, c = e[..., 0], e[..., 1], e[..., 2]
    keep = (xp.abs(b) < 90.0) & (a > -180.0) & (a <= 180.0) & (c > -180.0) & (c <= 180.0)
    return xp.where(keep[..., None], e, matrix_to_euler(euler_to_matrix(e)))


def canonical_pose(pose):
    """Poses ``(..., 6)`` with their orientation triple made canonical (:func:`canonical_euler`)."""
    pose = _as_array(pose)
    return _xp(pose).concatenate([pose[..., :3], canonical_euler(pose[..., 3:])], -1)


def forward_vector(angles_deg):
    """Unit optical axis ``R @ (1, 0, 0)`` (the first column of R), ``(..., 3)``."""
    return euler_to_matrix(angles_deg)[..., :, 0]


def _transpose(R):
    return R.swapaxes(-1, -2) if _xp(R) is np else R.transpose(-1, -2)


def relative_pose(prev, cur, frame: PoseFrame = "world"):
    """Relative pose from ``prev`` to ``cur`` (both ``(..., 6)``) in the given frame.

    ``world``: ``(p_t - p_{t-1}, wrap(e_t - e_{t-1}))``.
    ``camera``: ``(R_{t-1}^T (p_t - p_{t-1}), euler(R_{t-1}^T R_t))``.
    """
    prev, cur = _as_array(prev), _as_array(cur)
    xp = _xp(prev)
    dp = cur[..., :3] - prev[..., :3]
    if frame == "world":
        de = wrap_deg(cur[..., 3:] - prev[..., 3:])
    elif frame == "camera":
        Rp_T = _transpose(euler_to_matrix(prev[..., 3:]))
        dp = _matmul(Rp_T, dp[..., None])[..., 0]
        de = matrix_to_euler(_matmul(Rp_T, euler_to_matrix(cur[..., 3:])))
    else:
        raise ValueError(f"pose frame {frame!r} is not one of {', '.join(POSE_FRAMES)}")
    return xp.concatenate([dp, de], -1)


def relative_trajectory(poses, frame: PoseFrame = "world"):
    """Absolute poses ``(..., N, 6)`` -> relative poses ``(..., N-1, 6)`` between neighbours."""
    poses = _as_array(poses)
    return relative_pose(poses[..., :-1, :], poses[..., 1:, :], frame)


def compose(pose, delta, frame: PoseFrame = "world"):
    """Apply one relative pose ``delta`` to ``pose`` (both ``(..., 6)``); inverse of :func:`relative_pose`."""
    pose, delta = _as_array(pose), _as_array(delta)
    xp = _xp(pose)
    if frame == "world":
        return xp.concatenate([pose[..., :3] + delta[..., :3], wrap_deg(pose[..., 3:] + delta[..., 3:])], -1)
    if frame != "camera":
        raise ValueError(f"pose frame {frame!r} is not one of {', '.join(POSE_FRAMES)}")
    R = euler_to_matrix(pose[..., 3:])
    p = pose[..., :3] + _matmul(R, delta[..., :3, None])[..., 0]
    return xp.concatenate([p, matrix_to_euler(_matmul(R, euler_to_matrix(delta[..., 3:])))], -1)


def accumulate(start, deltas, frame: PoseFrame = "world"):
    """Chain relative poses: ``start (..., 6)`` and ``deltas (..., N, 6)`` -> poses ``(..., N+1, 6)``.

    ``world`` sums the differences (P_L = P_0 + sum dP_t, angles wrapped at the
    end); ``camera`` composes rigid motions one step at a time.
    """
    start, deltas = _as_array(start), _as_array(deltas)
    xp = _xp(start)
    if frame == "world":
        csum = xp.cumsum(deltas, -2)
        out = start[..., None, :] + xp.concatenate([xp.zeros_like(deltas[..., :1, :]), csum], -2)
        return xp.concatenate([out[..., :3], wrap_deg(out[..., 3:])], -1)
    if frame != "camera":
        raise ValueError(f"pose frame {frame!r} is not one of {', '.join(POSE_FRAMES)}")
    # Compose in matrix form so no Euler round trip accumulates error.
    R = euler_to_matrix(start[..., 3:])
    p = start[..., :3]
    dR = euler_to_matrix(deltas[..., 3:])
    positions, rotations = [p], [R]
    for t in range(deltas.shape[-2]):
        p = p + _matmul(R, deltas[..., t, :3, None])[..., 0]
        R = _matmul(R, dR[..., t, :, :])
        positions.append(p)
        rotations.append(R)
    pos = xp.stack(positions, -2)
    ang = matrix_to_euler(xp.stack(rotations, -3))
    return xp.concatenate([pos, ang], -1)


def look_at_rotation(forward, up_hint):
    """Rotation whose columns are (forward, left, up) from a view direction and an up hint.

    ``forward`` and ``up_hint`` are ``(..., 3)``; ``up_hint`` need not be
    orthogonal to ``forward`` but must not be parallel to it.
    """
    f = _as_array(forward)
    xp = _xp(f)
    f = f / xp.sqrt((f * f).sum(-1))[..., None]
    u = _as_array(up_hint)
    u = u - (u * f).sum(-1)[..., None] * f
    norm = xp.sqrt((u * u).sum(-1))[..., None]
    if bool((norm < 1e-12).any()):
        raise ValueError("look_at_rotation: the up hint is parallel to the view direction")
    u = u / norm
    left = xp.linalg.cross(u, f)
    return xp.stack([f, left, u], -1)


def roll_about_forward(R, roll_deg):
    """Roll a camera about its own optical axis by ``roll_deg`` (right-handed about +x)."""
    R = _as_array(R)
    xp = _xp(R)
    if xp is np:
        roll = np.asarray(roll_deg, dtype=np.float64)
    else:
        roll = xp.as_tensor(roll_deg, dtype=R.dtype, device=R.device)
    zeros = xp.zeros_like(roll)
    return _matmul(R, euler_to_matrix(xp.stack([roll, zeros, zeros], -1)))
