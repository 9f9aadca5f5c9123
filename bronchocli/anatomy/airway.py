"""The airway model every anatomy source produces and the renderer and trajectories consume.

Coordinates are the anatomy's own millimetres. The voxel grid (``origin_mm``,
``spacing_mm``) defines the world frame of poses: ``voxel = (mm - origin) / spacing``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import hostfree as hf
from ._vtk import poly_from_state, poly_state


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
        return float(hf.norm(np.diff(self.points, axis=0)).sum())


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
        return np.concatenate([[0.0], np.cumsum(hf.norm(np.diff(self.points, axis=0)))])

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
    # The source's own lumen surface (vtkPolyData in mm) for volume and mesh anatomies;
    # None for centreline sources, whose surface ``lumen_surface`` builds from the radii.
    surface: Any = field(default=None, repr=False, compare=False)
    # Derived data computed on demand (e.g. the centreline KD-tree); not part of the model.
    cache: dict = field(default_factory=dict, repr=False, compare=False)

    def path_to(self, branch: int) -> list[int]:
        """Branch indices from the trachea down to ``branch`` (inclusive)."""
        path = [branch]
        while self.branches[path[-1]].parent is not None:
            path.append(self.branches[path[-1]].parent)
        return path[::-1]

    def leaves(self, under: int = 0) -> list[int]:
        """Indices of the leaf branches in the subtree rooted at branch ``under``."""
        out, stack = [], [under]
        while stack:
            b = stack.pop()
            kids = self.branches[b].children
            if kids:
                stack.extend(kids)
            else:
                out.append(b)
        return out

    @property
    def max_generation(self) -> int:
        return max(b.generation for b in self.branches)

    def __getstate__(self) -> dict:
        """Picklable (for worker processes): the VTK surface travels as numpy arrays, the cache stays."""
        state = dict(self.__dict__)
        state["cache"] = {}
        if self.surface is not None:

            state["surface"] = ("vtkPolyData", poly_state(self.surface))
        return state

    def __setstate__(self, state: dict) -> None:
        surface = state.get("surface")
        if isinstance(surface, tuple) and surface[0] == "vtkPolyData":

            state = {**state, "surface": poly_from_state(surface[1])}
        self.__dict__.update(state)

    def to_voxels(self, mm: np.ndarray) -> np.ndarray:
        return (np.asarray(mm, dtype=np.float64) - self.origin_mm) / self.spacing_mm

    def to_mm(self, voxels: np.ndarray) -> np.ndarray:
        return np.asarray(voxels, dtype=np.float64) * self.spacing_mm + self.origin_mm
