"""Lumen geometry queries for trajectory sampling and ground-truth checks (numpy/SciPy only, no VTK).

The centreline is resampled densely (``STEP_MM``) and indexed with a KD-tree;
the nearest sample's two adjacent segments then give the exact distance to the
centreline polyline and the radius interpolated at the closest point. A query
returns, per point, that distance, the lumen radius there, the branch and the
closest centreline point. "Inside the lumen" means ``distance + margin < radius``.
Near a bifurcation the nearest centreline may be the thinner child's, so the
test is conservative there (it never calls a wall point inside).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from .. import hostfree as hf
from .airway import AirwayTree, LobePath

STEP_MM = 0.1
NEIGHBOURS = 4  # nearest samples whose adjacent segments are measured exactly


class Nearest(NamedTuple):
    distance_mm: np.ndarray  # (N,) distance to the centreline
    radius_mm: np.ndarray  # (N,) lumen radius at the closest centreline point
    branch: np.ndarray  # (N,) branch index of that point
    point_mm: np.ndarray  # (N, 3) the closest centreline point


class Lumen:
    """KD-tree over a densely resampled centreline of ``tree`` (build once, query many times)."""

    def __init__(self, tree: AirwayTree, step_mm: float = STEP_MM):
        pts, rad, ids, last = [], [], [], []
        for i, b in enumerate(tree.branches):
            p, r = resample(b.points, b.radii, step_mm)
            pts.append(p)
            rad.append(r)
            ids.append(np.full(len(p), i))
            flags = np.zeros(len(p), dtype=bool)
            flags[-1] = True
            last.append(flags)
        self.points = np.concatenate(pts)
        self.radii = np.concatenate(rad)
        self.branch = np.concatenate(ids)
        self._last = np.concatenate(last)  # sample ends its branch: no segment to the next sample
        self.kdtree = cKDTree(self.points)

    def nearest(self, points_mm: np.ndarray) -> Nearest:
        q = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
        _, nearest = self.kdtree.query(q, k=min(NEIGHBOURS, len(self.points)))
        nearest = nearest.reshape(len(q), -1)
        best = [np.full(len(q), np.inf), np.zeros(len(q)), np.zeros((len(q), 3)), np.zeros(len(q), dtype=int)]
        # Joints hold one sample per branch at the same spot: look at the segments around a few
        # nearest samples, not just the first, or a joint sample of the wrong branch decides.
        for idx in nearest.T:
            for a, b in ((idx - 1, idx), (idx, idx + 1)):
                a, b = np.clip(a, 0, len(self.points) - 1), np.clip(b, 0, len(self.points) - 1)
                valid = (a != b) & ~self._last[a]
                a, b = np.where(valid, a, idx), np.where(valid, b, idx)
                ab = self.points[b] - self.points[a]
                denom = np.maximum(hf.dot(ab, ab), 1e-18)
                t = np.clip(hf.dot(q - self.points[a], ab) / denom, 0.0, 1.0)
                closest = self.points[a] + t[:, None] * ab
                dist = hf.norm(q - closest)
                better = dist < best[0]
                best[0] = np.where(better, dist, best[0])
                best[1] = np.where(better, (1 - t) * self.radii[a] + t * self.radii[b], best[1])
                best[2] = np.where(better[:, None], closest, best[2])
                best[3] = np.where(better, self.branch[idx], best[3])
        return Nearest(*best[:2], best[3], best[2])

    def inside(self, points_mm: np.ndarray, margin_mm: float = 0.0) -> np.ndarray:
        """True where a point lies at least ``margin_mm`` inside the wall (by the nearest centreline)."""
        n = self.nearest(points_mm)
        return n.distance_mm + margin_mm < n.radius_mm

    def clearance(self, points_mm: np.ndarray) -> np.ndarray:
        """Estimated distance to the wall (mm): local radius minus distance to the centreline."""
        n = self.nearest(points_mm)
        return n.radius_mm - n.distance_mm


def lumen_index(tree: AirwayTree) -> Lumen:
    """The tree's ``Lumen``, built on first use and cached on the tree."""
    if "lumen" not in tree.cache:
        tree.cache["lumen"] = Lumen(tree)
    return tree.cache["lumen"]


def centreline_distance(tree: AirwayTree, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance to the centreline, local lumen radius), both (N,) in mm, for (N, 3) points in mm."""
    n = lumen_index(tree).nearest(points_mm)
    return n.distance_mm, n.radius_mm


def resample(points: np.ndarray, values: np.ndarray, step_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A polyline and its per-point values at even arc-length steps of at most ``step_mm``, ends kept."""
    points = np.asarray(points, dtype=np.float64)
    s = np.concatenate([[0.0], np.cumsum(hf.norm(np.diff(points, axis=0)))])
    n = max(int(np.ceil(s[-1] / step_mm)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    pts = np.stack([np.interp(t, s, points[:, i]) for i in range(3)], axis=1)
    return pts, np.interp(t, s, values)


def path_at(path: LobePath, arc_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3), radii (N,)) of a lobe path at arc lengths ``arc_mm`` (clipped to the path)."""
    s = path.arc_length
    a = np.clip(np.asarray(arc_mm, dtype=np.float64), 0.0, s[-1])
    pts = np.stack([np.interp(a, s, path.points[:, i]) for i in range(3)], axis=-1)
    return pts, np.interp(a, s, path.radii)
