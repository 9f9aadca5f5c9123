"""Pinhole intrinsics that match VTK's perspective camera, and the pixel <-> ray maps.

VTK's ``ViewAngle`` is the *vertical* field of view and spans the full image
height from the top edge of the first row to the bottom edge of the last, so
with pixel centres at integer coordinates (u right, v down, origin at the
centre of the top-left pixel)::

    fy = (H / 2) / tan(fov / 2),   fx = fy (square pixels),
    cx = (W - 1) / 2,              cy = (H - 1) / 2.

A camera-frame point ``(x, y, z)`` (x forward, y left, z up, docs/conventions.md)
projects to ``u = cx - fx * y / x``, ``v = cy - fy * z / x``. Pure NumPy: the
dataset reader and tests use it without VTK.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

NEAR_MM = 0.2  # near clipping plane: small, the camera may be ~0.3 mm from the wall
FAR_MM = 400.0  # far plane: beyond any airway length


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera of a ``width x height`` frame (pixels) rendered with ``fov_deg`` vertical field of view."""

    width: int
    height: int
    fov_deg: float
    fx: float
    fy: float
    cx: float
    cy: float
    near_mm: float = NEAR_MM
    far_mm: float = FAR_MM

    def as_json(self) -> dict:
        """The ``camera`` block of dataset.json (image size is stored separately)."""
        d = asdict(self)
        del d["width"], d["height"]
        return d


def intrinsics(width: int, height: int | None = None, fov_deg: float = 70.0) -> Intrinsics:
    """Intrinsics consistent with a VTK camera of view angle ``fov_deg`` rendering ``width x height``."""
    height = width if height is None else height
    if not (0.0 < fov_deg < 180.0):
        raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
    f = (height / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    return Intrinsics(width, height, float(fov_deg), f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def project(points_cam: np.ndarray, cam: Intrinsics) -> np.ndarray:
    """Camera-frame points ``(..., 3)`` (x forward, y left, z up) -> pixel coordinates ``(..., 2)`` (u, v)."""
    p = np.asarray(points_cam, dtype=np.float64)
    x = p[..., 0]
    return np.stack([cam.cx - cam.fx * p[..., 1] / x, cam.cy - cam.fy * p[..., 2] / x], -1)


def pixel_rays(uv: np.ndarray, cam: Intrinsics) -> np.ndarray:
    """Pixel coordinates ``(..., 2)`` -> unit camera-frame view directions ``(..., 3)``."""
    uv = np.asarray(uv, dtype=np.float64)
    d = np.stack([np.ones(uv.shape[:-1]), -(uv[..., 0] - cam.cx) / cam.fx, -(uv[..., 1] - cam.cy) / cam.fy], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
