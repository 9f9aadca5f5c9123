"""Airway anatomy: one centreline-graph model from procedural trees, graphs, volumes or meshes; lobe paths.

``load_anatomy(source, ...)`` is the entry point: ``"procedural"`` (seeded) or a
file path (``.vtu``/``.vtp`` graphs, ``.nii``/``.nii.gz``/``.mhd``/``.nrrd``
label volumes, ``.stl``/``.obj``/``.vtp`` surface meshes). It returns an
``AirwayTree`` rooted at the trachea with its four lobe paths. ``lumen_surface``
turns a tree into the watertight mesh the renderer draws; ``centreline_distance``
and ``Lumen`` answer "is this point inside the airway?". Only dataset generation
uses this package (it loads VTK). See docs/anatomy.md.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError
from .airway import AirwayTree, Branch, LobePath
from .lobes import LOBES, find_lobe_paths, lobe_path, main_bronchi, up_vector
from .lumen import Lumen, Nearest, centreline_distance, lumen_index, path_at, resample
from .procedural import Morphometry, procedural_tree
from .readers import ALLOWED_EXTS, read_anatomy_file, save_centreline
from .surface import lumen_surface

__all__ = [
    "ALLOWED_EXTS",
    "LOBES",
    "AirwayTree",
    "Branch",
    "LobePath",
    "Lumen",
    "Morphometry",
    "Nearest",
    "centreline_distance",
    "find_lobe_paths",
    "load_anatomy",
    "lobe_path",
    "lumen_index",
    "lumen_surface",
    "main_bronchi",
    "path_at",
    "procedural_tree",
    "resample",
    "save_centreline",
    "up_vector",
]

PROCEDURAL = "procedural"


def load_anatomy(source: str | Path, *, seed: int = 0, voxel_mm: float = 0.5,
                 centreline: str | Path | None = None, lobe_generation: int | None = None) -> AirwayTree:
    """The airway tree of ``source`` with its lobe paths ``ur``, ``br``, ``ul``, ``bl``.

    ``source``: ``"procedural"`` (patient ``seed``) or a path to an anatomy file.
    ``voxel_mm``: the world voxel size for procedural, graph and mesh anatomies (volumes
    keep their own grid). ``centreline``: a .vtu/.vtp graph to use for a volume or mesh
    instead of skeletonising it (ignored for the other sources). ``lobe_generation``:
    end each lobe path at this generation at the latest (None: the full rule).
    Raises DataError (one line naming the file) for bad input.
    """
    if not voxel_mm > 0:
        raise ConfigError(f"voxel_mm must be > 0, got {voxel_mm}")
    if str(source) == PROCEDURAL:
        tree = procedural_tree(seed=seed, voxel_mm=voxel_mm)
    else:
        tree = read_anatomy_file(source, voxel_mm=voxel_mm, centreline=centreline)
    tree.lobe_paths = find_lobe_paths(tree, max_generation=lobe_generation)
    return tree


