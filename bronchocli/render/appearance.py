"""How the lumen looks: normals, mucosa colours, and spatial blocks for fast culling.

The anatomy package makes the watertight lumen surface (mm); this module
readies it for the renderer. ``prepare_surface`` adds smooth point normals and,
with ``realism.texture``, per-vertex mucosa colours from seeded 3-D value
noise (blotches plus a ridged "vessel" network), so the look is deterministic
per patient and costs nothing at render time. ``split_blocks`` cuts the mesh
into spatial blocks (one actor each) so VTK's frustum culling skips the
airways behind and beside the camera.
"""

from __future__ import annotations

import numpy as np

from . import configure_environment

configure_environment()

from vtkmodules.util.numpy_support import (  # noqa: E402
    numpy_to_vtk,
    numpy_to_vtkIdTypeArray,
    vtk_to_numpy,
)
from vtkmodules.vtkCommonCore import vtkPoints  # noqa: E402
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData  # noqa: E402
from vtkmodules.vtkFiltersCore import vtkPolyDataNormals, vtkTriangleFilter  # noqa: E402

AIRWAY_RGB = (0.96, 0.60, 0.48)  # diffuse mucosa colour
VESSEL_RGB = (0.62, 0.18, 0.20)  # darker red for the vessel network of the texture
COLOUR_ARRAY = "mucosa_rgb"


# -- value noise ---------------------------------------------------------------


def _hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice point (64-bit mix hash)."""
    with np.errstate(over="ignore"):
        h = (ix.astype(np.uint64) * np.uint64(0x9E3779B185EBCA87)
             ^ iy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
             ^ iz.astype(np.uint64) * np.uint64(0x165667B19E3779F9)
             ^ np.uint64(seed & 0xFFFFFFFF) * np.uint64(0x27D4EB2F165667C5))
        h ^= h >> np.uint64(33)
        h *= np.uint64(0xFF51AFD7ED558CCD)
        h ^= h >> np.uint64(33)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def value_noise(points: np.ndarray, scale_mm: float, seed: int) -> np.ndarray:
    """Smooth 3-D value noise in [0, 1] at ``points (N, 3)`` with feature size ``scale_mm``."""
    p = np.asarray(points, dtype=np.float64) / scale_mm
    base = np.floor(p)
    f = p - base
    f = f * f * (3.0 - 2.0 * f)  # smoothstep: C1 across lattice cells
    i = base.astype(np.int64) + (1 << 20)  # keep lattice indices positive for the hash
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1.0 - f[:, 0]
        for dy in (0, 1):
            wy = f[:, 1] if dy else 1.0 - f[:, 1]
            for dz in (0, 1):
                wz = f[:, 2] if dz else 1.0 - f[:, 2]
                out += wx * wy * wz * _hash01(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
    return out


def mucosa_colours(points: np.ndarray, seed: int) -> np.ndarray:
    """Per-vertex RGB (uint8, ``(N, 3)``) of a mottled mucosa with a faint vessel network."""
    blotch = 0.6 * value_noise(points, 6.0, seed) + 0.4 * value_noise(points, 2.0, seed + 1)
    ridge = np.abs(2.0 * value_noise(points, 3.5, seed + 2) - 1.0)
    vessel = np.exp(-((ridge / 0.12) ** 2)) * value_noise(points, 10.0, seed + 3)  # vessels in some areas only
    rgb = np.asarray(AIRWAY_RGB) * (0.85 + 0.3 * blotch)[:, None]
    rgb = rgb * (1.0 - 0.55 * vessel[:, None]) + np.asarray(VESSEL_RGB) * 0.55 * vessel[:, None]
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)


# -- mesh helpers ----------------------------------------------------------------


def triangles(poly: vtkPolyData) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(N, 3)`` and triangle vertex indices ``(M, 3)`` of a triangulated polydata."""
    if poly.GetNumberOfPolys() != poly.GetNumberOfCells() or poly.GetPolys().GetMaxCellSize() > 3:
        tri = vtkTriangleFilter()
        tri.SetInputData(poly)
        tri.PassLinesOff()
        tri.PassVertsOff()
        tri.Update()
        poly = tri.GetOutput()
    pts = vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    conn = vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)
    return pts, conn


def prepare_surface(poly: vtkPolyData, *, texture: bool, seed: int = 0) -> vtkPolyData:
    """A render-ready copy of ``poly``: triangles only, smooth point normals, mucosa colours if ``texture``."""
    tri = vtkTriangleFilter()
    tri.SetInputData(poly)
    tri.PassLinesOff()
    tri.PassVertsOff()
    normals = vtkPolyDataNormals()
    normals.SetInputConnection(tri.GetOutputPort())
    normals.SplittingOff()  # no hard edges inside an airway
    normals.ConsistencyOn()
    normals.ComputePointNormalsOn()
    normals.ComputeCellNormalsOff()
    normals.Update()
    out = vtkPolyData()
    out.DeepCopy(normals.GetOutput())
    if out.GetNumberOfPolys() == 0:
        raise ValueError("the lumen surface has no triangles")
    if texture:
        pts = vtk_to_numpy(out.GetPoints().GetData()).astype(np.float64)
        arr = numpy_to_vtk(mucosa_colours(pts, seed), deep=True)
        arr.SetName(COLOUR_ARRAY)
        out.GetPointData().SetScalars(arr)
    else:
        out.GetPointData().SetScalars(None)
    return out


def _subset(poly: vtkPolyData, pts: np.ndarray, tris: np.ndarray) -> vtkPolyData:
    """A compact polydata of the triangles ``tris`` (indices into ``poly``'s points), point data carried over."""
    used, inverse = np.unique(tris, return_inverse=True)
    block = vtkPolyData()
    points = vtkPoints()
    points.SetData(numpy_to_vtk(pts[used].astype(np.float32), deep=True))
    block.SetPoints(points)
    cells = vtkCellArray()
    offsets = np.arange(0, 3 * len(tris) + 1, 3, dtype=np.int64)
    cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_to_vtkIdTypeArray(inverse.reshape(-1).astype(np.int64), deep=True))
    block.SetPolys(cells)
    src = poly.GetPointData()
    for k in range(src.GetNumberOfArrays()):
        arr = src.GetArray(k)
        if arr is None:
            continue
        values = numpy_to_vtk(np.ascontiguousarray(vtk_to_numpy(arr)[used]), deep=True)
        values.SetName(arr.GetName())
        block.GetPointData().AddArray(values)
    if src.GetNormals() is not None:
        block.GetPointData().SetActiveNormals(src.GetNormals().GetName())
    if src.GetScalars() is not None:
        block.GetPointData().SetActiveScalars(src.GetScalars().GetName())
    return block


def split_blocks(poly: vtkPolyData, blocks: int) -> list[vtkPolyData]:
    """Cut ``poly`` into about ``blocks`` spatially compact pieces (k-d split of triangle centroids)."""
    pts, tris = triangles(poly)
    if blocks <= 1 or len(tris) < 2 * blocks:
        return [poly]
    groups = [np.arange(len(tris))]
    centroids = pts[tris].mean(1)
    while len(groups) < blocks:
        groups.sort(key=len)
        g = groups.pop()  # split the largest group along its longest extent
        c = centroids[g]
        axis = int(np.argmax(c.max(0) - c.min(0)))
        order = g[np.argsort(c[:, axis], kind="stable")]
        groups += [order[: len(order) // 2], order[len(order) // 2:]]
    groups.sort(key=lambda g: int(g.min()))  # stable actor order
    return [_subset(poly, pts, tris[np.sort(g)]) for g in groups]
