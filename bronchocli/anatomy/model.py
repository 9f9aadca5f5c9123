"""The airway model every anatomy source produces and the renderer and trajectories consume.

Coordinates are the anatomy's own millimetres. The voxel grid (``origin_mm``,
``spacing_mm``) defines the world frame of poses: ``voxel = (mm - origin) / spacing``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Branch:
    """One airway segment between two bifurcations (or a bifurcation and an end)."""

    points: np.ndarray  # (M, 3) centreline polyline in mm, from the parent end towards the leaves
    radii: np.ndarray  # (M,) lumen radius in mm at each point
    parent: int | None  # index into AirwayTree.branches; None for the trachea
    children: list[int] = field(default_factory=list)
    generation: int = 0  # trachea 0, main bronchi 1, lobar 2, ...

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())


@dataclass
class LobePath:
    """A path from the trachea entrance to a distal airway of one lobe."""

    lobe: str  # 'ur', 'br', 'ul', 'bl'
    branches: list[int]  # branch indices from the trachea down
    points: np.ndarray  # (K, 3) concatenated centreline in mm, duplicates at joints removed
    radii: np.ndarray  # (K,)

    @property
    def arc_length(self) -> np.ndarray:
        """Cumulative arc length in mm at each point, starting at 0."""
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.points, axis=0), axis=1))])

    @property
    def generation(self) -> int:
        return len(self.branches) - 1


@dataclass
class AirwayTree:
    """Centreline graph with radii, rooted at the trachea (branch 0)."""

    branches: list[Branch]
    origin_mm: np.ndarray  # (3,) voxel grid origin
    spacing_mm: np.ndarray  # (3,) voxel size
    name: str = "airway"
    lobe_paths: dict[str, LobePath] = field(default_factory=dict)

    def to_voxels(self, mm: np.ndarray) -> np.ndarray:
        return (np.asarray(mm, dtype=np.float64) - self.origin_mm) / self.spacing_mm

    def to_mm(self, voxels: np.ndarray) -> np.ndarray:
        return np.asarray(voxels, dtype=np.float64) * self.spacing_mm + self.origin_mm
