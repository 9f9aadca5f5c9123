"""Centreline graph (points, radii, edges) -> AirwayTree rooted at the trachea.

Every file source ends here: graph files directly, volumes and meshes through
their skeleton. Steps: merge coincident points, check the graph is one piece,
break cycles with a minimum spanning tree (skeletons have small loops at
junctions), pick the root (the trachea entrance), split into branches at nodes
of degree != 2, number the generations, smooth the radii along each branch.

Root rule: the end point (degree 1) of the widest terminal branch, widest by
median radius; when several terminal branches are within ``ROOT_RADIUS_TIE``
of the widest, the highest of them (largest z) wins. The trachea is by far
the widest terminal branch of any airway tree, so the rule does not depend on
the file's orientation; z only breaks near-ties (e.g. in tiny synthetic trees).
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from ..errors import DataError
from .airway import AirwayTree, Branch

MERGE_TOL_MM = 1e-3  # points closer than this are one node (centreline files often repeat junction points)
ROOT_RADIUS_TIE = 0.8  # terminal branches at least this fraction of the widest compete on height
RADIUS_SIGMA_MM = 2.0  # Gaussian smoothing of radii along each branch (point-to-point noise shows as rings)
GRID_MARGIN_MM = 5.0  # free space between the lumen and the voxel grid's origin for graph/mesh sources


def tree_from_graph(points: np.ndarray, radii: np.ndarray, edges: np.ndarray, *, name: str, source: str,
                    voxel_mm: float = 0.5, origin_mm: np.ndarray | None = None,
                    spacing_mm: np.ndarray | None = None, smooth_points_mm: float = 0.0) -> AirwayTree:
    """Build the rooted branch tree of a centreline graph (coordinates and radii in mm).

    ``origin_mm``/``spacing_mm`` give the voxel grid when the source has one (volumes);
    otherwise the grid has ``voxel_mm`` spacing and its origin ``GRID_MARGIN_MM`` plus the
    largest radius below the points' bounding box. ``source`` names the file in errors.
    """
    points, radii, edges = _validated(points, radii, edges, source)
    points, radii, edges = _merge_coincident(points, radii, edges)
    n = len(points)
    _check_connected(n, edges, source)
    if len(edges) > n - 1:
        edges = _spanning_tree(points, edges, n)
    adjacency = _adjacency(n, edges)
    root = find_root(points, radii, adjacency)
    branches = _split(root, adjacency, points, radii)
    for b in branches:
        b.radii = smooth_along(b.radii, b.points, RADIUS_SIGMA_MM)
        if smooth_points_mm > 0 and len(b.points) > 2:
            inner = smooth_along(b.points, b.points, smooth_points_mm)
            b.points = np.concatenate([b.points[:1], inner[1:-1], b.points[-1:]])
    if spacing_mm is None:
        spacing_mm, origin_mm = grid_around(points, radii, voxel_mm)
    return AirwayTree(branches=branches, origin_mm=np.asarray(origin_mm, dtype=np.float64),
                      spacing_mm=np.asarray(spacing_mm, dtype=np.float64), name=name)


def grid_around(points: np.ndarray, radii: np.ndarray, voxel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(spacing, origin) of an isotropic grid whose origin lies a margin below the points' bounding box."""
    margin = np.ceil((float(np.max(radii)) + GRID_MARGIN_MM) / voxel_mm) * voxel_mm
    return np.full(3, float(voxel_mm)), np.asarray(points).min(axis=0) - margin


def _validated(points, radii, edges, source: str):
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).ravel()
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if len(edges) == 0:
        raise DataError(f"{source}: no centreline lines (edges) found; expected a polyline graph")
    if not np.all(np.isfinite(points)) or not np.all(np.isfinite(radii)):
        raise DataError(f"{source}: centreline points or radii contain NaN/inf")
    if len(radii) != len(points):
        raise DataError(f"{source}: {len(radii)} radii for {len(points)} points; need one radius per point")
    positive = radii[radii > 0]
    if len(positive) == 0:
        raise DataError(f"{source}: every radius is <= 0; the radius array must hold lumen radii in mm")
    # Zero radii at leaf tips are common in centreline files: give them the smallest real radius.
    return points, np.where(radii > 0, radii, positive.min()), edges


def _merge_coincident(points, radii, edges):
    """Fuse points closer than MERGE_TOL_MM, drop unused points, self-loops and duplicate edges."""
    pairs = cKDTree(points).query_pairs(MERGE_TOL_MM, output_type="ndarray")
    if len(pairs):
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
        _, label = connected_components(g, directed=False)
    else:
        label = np.arange(len(points))
    edges = label[edges]
    edges = np.sort(edges[edges[:, 0] != edges[:, 1]], axis=1)
    edges = np.unique(edges, axis=0)
    used, inverse = np.unique(edges, return_inverse=True)
    # Representative point of each merged group: its first member (they are within MERGE_TOL_MM).
    first = np.full(label.max() + 1, -1)
    first[label[::-1]] = np.arange(len(label))[::-1]
    reps = first[used]
    return points[reps], radii[reps], inverse.reshape(-1, 2)


def _check_connected(n: int, edges: np.ndarray, source: str) -> None:
    g = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    count, label = connected_components(g, directed=False)
    if count > 1:
        sizes = np.sort(np.bincount(label))[::-1]
        shown = ", ".join(map(str, sizes[:5])) + (", ..." if count > 5 else "")
        raise DataError(f"{source}: the centreline graph is disconnected ({count} pieces of {shown} points); "
                        "expected one connected airway tree")


def _spanning_tree(points: np.ndarray, edges: np.ndarray, n: int) -> np.ndarray:
    """Break cycles: keep the minimum spanning tree, edges weighted by their length."""
    length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1) + 1e-9
    mst = minimum_spanning_tree(coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(n, n))).tocoo()
    return np.stack([mst.row, mst.col], axis=1).astype(np.int64)


def _adjacency(n: int, edges: np.ndarray) -> list[list[int]]:
    adjacency: list[list[int]] = [[] for _ in range(n)]
    for a, b in edges.tolist():
        adjacency[a].append(b)
        adjacency[b].append(a)
    return adjacency


def _walk(start: int, nxt: int, adjacency: list[list[int]]) -> list[int]:
    """Nodes from ``start`` through ``nxt`` along degree-2 nodes to the next node of degree != 2."""
    path, prev, cur = [start, nxt], start, nxt
    while len(adjacency[cur]) == 2:
        a, b = adjacency[cur]
        prev, cur = cur, (b if a == prev else a)
        path.append(cur)
    return path


def find_root(points: np.ndarray, radii: np.ndarray, adjacency: list[list[int]]) -> int:
    """The trachea entrance: see the module docstring for the rule."""
    ends = [i for i, nb in enumerate(adjacency) if len(nb) == 1]
    widths = []
    for e in ends:
        path = _walk(e, adjacency[e][0], adjacency)
        inner = path[:-1] if len(adjacency[path[-1]]) != 1 else path
        widths.append(float(np.median(radii[inner])))
    widths = np.asarray(widths)
    candidates = [e for e, w in zip(ends, widths) if w >= ROOT_RADIUS_TIE * widths.max()]
    return max(candidates, key=lambda e: points[e, 2])


def _split(root: int, adjacency: list[list[int]], points: np.ndarray, radii: np.ndarray) -> list[Branch]:
    """Breadth-first split into branches: parents come before children, branch 0 is the trachea."""
    branches: list[Branch] = []
    queue = deque([(root, adjacency[root][0], None)])
    while queue:
        start, nxt, parent = queue.popleft()
        path = _walk(start, nxt, adjacency)
        generation = 0 if parent is None else branches[parent].generation + 1
        index = len(branches)
        branches.append(Branch(points=points[path].copy(), radii=radii[path].copy(), parent=parent,
                               generation=generation))
        if parent is not None:
            branches[parent].children.append(index)
        end, before = path[-1], path[-2]
        queue.extend((end, nb, index) for nb in adjacency[end] if nb != before)
    return branches


def smooth_along(values: np.ndarray, points: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Gaussian smoothing of per-point ``values`` over the arc length of the polyline ``points``.

    Weights are normalised per point, so the ends are not pulled towards zero.
    """
    values = np.asarray(values, dtype=np.float64)
    if len(values) < 3 or sigma_mm <= 0:
        return values.copy()
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    out = np.empty_like(values)
    for lo in range(0, len(s), 1024):  # chunks keep the weight matrix small for long branches
        w = np.exp(-0.5 * ((s[lo:lo + 1024, None] - s[None, :]) / sigma_mm) ** 2)
        w /= w.sum(axis=1, keepdims=True)
        out[lo:lo + 1024] = w @ values
    return out

