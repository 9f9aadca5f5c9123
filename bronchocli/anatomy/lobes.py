"""Lobe paths ``ur``, ``br``, ``ul``, ``bl``: found from the tree's geometry, not its coordinates.

Rule (docs/anatomy.md has the reasoning):

1. *Up* (superior) is +z when the trachea's axis (carina -> entrance) is within 45° of
   +z, i.e. the file is in a patient frame with z along the body (DICOM-style volumes,
   the real tree, procedural trees); otherwise the trachea's axis itself. Heights are
   projections on it. Left/right never uses coordinates.
2. The main bronchi are the carina's two children with the largest subtrees (total
   centreline length). The right main bronchus is chosen by majority vote of three
   textbook differences: it is shorter (to its next bifurcation), steeper (larger
   downward component of its chord) and wider (median radius) than the left.
3. At each main bronchus's first real bifurcation (a child that is a lone leaf shorter
   than twice the parent's radius is a spur and is skipped), the child whose leaves
   have the higher mean height is the upper lobe, the lower one the lower lobe.
4. The upper path ends at the most superior leaf of the upper subtree, the lower path
   at the most inferior leaf of the lower subtree. Paths start at the trachea entrance.

A main bronchus that does not branch gives both of its lobes the same path (a
degenerate tree; the generator still works, the paths just coincide).
"""

from __future__ import annotations

import numpy as np

from .. import hostfree as hf
from ..errors import ConfigError, DataError
from .airway import AirwayTree, LobePath

LOBES = ("ur", "br", "ul", "bl")
SPUR_RADII = 2.0  # a lone leaf child shorter than this many parent radii is a spur, not a lobar bronchus
PATIENT_FRAME_DEG = 45.0  # a trachea this close to +z means the file's z is the body's long axis


def up_vector(tree: AirwayTree) -> np.ndarray:
    """The superior direction: +z when the trachea axis is within ``PATIENT_FRAME_DEG`` of it (the
    file is in a patient frame, z superior), else the trachea axis from the carina to the entrance."""
    pts = tree.branches[0].points
    v = pts[0] - pts[-1]
    v = v / (hf.norm(v) or 1.0)
    return np.array([0.0, 0.0, 1.0]) if v[2] >= hf.cos(np.radians(PATIENT_FRAME_DEG)) else v


def subtree(tree: AirwayTree, b: int) -> list[int]:
    out, stack = [], [b]
    while stack:
        i = stack.pop()
        out.append(i)
        stack.extend(tree.branches[i].children)
    return out


def _subtree_length(tree: AirwayTree, b: int) -> float:
    return sum(tree.branches[i].length for i in subtree(tree, b))


def main_bronchi(tree: AirwayTree) -> tuple[int, int]:
    """(right, left) main bronchus branch indices; see the module docstring, step 2."""
    kids = tree.branches[0].children
    if len(kids) < 2:
        raise DataError(f"{tree.name}: the trachea does not bifurcate; lobe paths need a carina")
    a, b = sorted(kids, key=lambda k: _subtree_length(tree, k), reverse=True)[:2]
    down = -up_vector(tree)
    votes = 0  # votes for "a is the right main bronchus"
    ba, bb = tree.branches[a], tree.branches[b]
    votes += ba.length < bb.length
    votes += hf.dot(_chord(ba.points), down) > hf.dot(_chord(bb.points), down)
    votes += np.median(ba.radii) > np.median(bb.radii)
    return (a, b) if votes >= 2 else (b, a)


def _chord(points: np.ndarray) -> np.ndarray:
    v = points[-1] - points[0]
    return v / (hf.norm(v) or 1.0)


def _real_children(tree: AirwayTree, b: int) -> list[int]:
    """Children of ``b`` without spurs, descending through bifurcations that only shed a spur."""
    while True:
        br = tree.branches[b]
        limit = SPUR_RADII * float(np.median(br.radii))
        real = [k for k in br.children
                if tree.branches[k].children or tree.branches[k].length >= limit]
        if len(real) != 1:
            return real if real else list(br.children)
        b = real[0]


def _height(tree: AirwayTree, leaf: int, up: np.ndarray) -> float:
    return float(hf.dot(tree.branches[leaf].points[-1], up))


def _upper_lower(tree: AirwayTree, main: int, up: np.ndarray) -> tuple[int, int]:
    """(leaf ending the upper path, leaf ending the lower path) of one lung."""
    kids = _real_children(tree, main)
    if not kids:
        return main, main
    mean_h = [np.mean([_height(tree, leaf, up) for leaf in tree.leaves(k)]) for k in kids]
    upper, lower = kids[int(np.argmax(mean_h))], kids[int(np.argmin(mean_h))]
    top = max(tree.leaves(upper), key=lambda leaf: _height(tree, leaf, up))
    bottom = min(tree.leaves(lower), key=lambda leaf: _height(tree, leaf, up))
    return top, bottom


def lobe_path(tree: AirwayTree, lobe: str, leaf: int) -> LobePath:
    """The path from the trachea entrance to the end of branch ``leaf``, joint duplicates removed."""
    ids = tree.path_to(leaf)
    pts, rad = [tree.branches[ids[0]].points], [tree.branches[ids[0]].radii]
    for i in ids[1:]:
        b = tree.branches[i]
        skip = 1 if np.allclose(b.points[0], pts[-1][-1]) else 0
        pts.append(b.points[skip:])
        rad.append(b.radii[skip:])
    return LobePath(lobe=lobe, branches=ids, points=np.concatenate(pts), radii=np.concatenate(rad))


def find_lobe_paths(tree: AirwayTree, max_generation: int | None = None) -> dict[str, LobePath]:
    """The four lobe paths of ``tree`` by the rule in the module docstring.

    ``max_generation`` cuts each path after its branch of that generation (>= 2, so the
    upper and lower paths of a lung still part); None keeps the rule's full depth.
    """
    if max_generation is not None and max_generation < 2:
        raise ConfigError(f"lobe path generation must be >= 2 (where upper and lower lobes part), got {max_generation}")
    up = up_vector(tree)
    right, left = main_bronchi(tree)
    ur, br = _upper_lower(tree, right, up)
    ul, bl = _upper_lower(tree, left, up)
    ends = {"ur": ur, "br": br, "ul": ul, "bl": bl}
    paths = {}
    for lobe in LOBES:
        ids = tree.path_to(ends[lobe])
        if max_generation is not None:
            ids = [i for i in ids if tree.branches[i].generation <= max_generation]
        paths[lobe] = lobe_path(tree, lobe, ids[-1])
    return paths
