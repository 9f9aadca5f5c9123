"""One watertight lumen surface (vtkPolyData, mm) for rendering, from radii or from the source's own mesh.

Centreline trees: the signed distance to the union of round cones along the
centreline (``sdf.py``) is contoured by Flying Edges at 0, reduced to its largest
connected piece (dropping enclosed bubbles where branches overlap), smoothed
with a windowed-sinc filter and decimated to a triangle budget (quadric
decimation; topology-preserving DecimatePro if that opened the surface). The
grid is as coarse as the thinnest airway allows: spacing
``clip(min radius / 1.5, voxel_mm, COARSEST_MM)``, so a tree whose airways are all
wide gets a coarser grid (fewer triangles, same look) while a tree with sub-mm
airways is contoured at ``voxel_mm``, where radii are clamped to one voxel so the
surface stays one piece. The grid is padded, so the surface is closed.

Volume and mesh anatomies keep their own surface (``tree.surface``); it is
cleaned and returned instead. Normals point into the lumen (towards the camera,
which is always inside).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy import ndimage
from vtkmodules.vtkFiltersCore import (
    vtkCleanPolyData,
    vtkDecimatePro,
    vtkFeatureEdges,
    vtkFlyingEdges3D,
    vtkPolyDataConnectivityFilter,
    vtkPolyDataNormals,
    vtkQuadricDecimation,
    vtkTriangleFilter,
    vtkWindowedSincPolyDataFilter,
)

from ._vtk import image_from_array, polydata_from_arrays, polydata_to_arrays
from .airway import AirwayTree
from .sdf import lumen_sdf_grid

COARSEST_MM = 1.0  # never contour coarser than this, however wide the airways
RADIUS_VOXELS = 1.5  # the thinnest airway spans at least this many voxels of radius when possible
SMOOTH_ITERATIONS = 15
SMOOTH_PASSBAND = 0.1
MAX_TRIANGLES = 60_000  # decimation target (benchmarks/README.md, "Rendering")
MAX_REDUCTION = 0.9  # never remove more than this fraction of the triangles


def lumen_surface(tree: AirwayTree, voxel_mm: float = 0.5, *, max_triangles: int | None = MAX_TRIANGLES):
    """The lumen of ``tree`` as one closed, connected triangle mesh in mm (vtkPolyData).

    ``voxel_mm`` is the finest contouring grid (see the module docstring for the grid
    actually used, ``surface_grid_mm``); ``max_triangles`` the decimation target (None:
    no decimation). Returns a cleaned copy of ``tree.surface`` when the anatomy brought
    its own surface.
    """
    if tree.surface is not None:
        return clean_surface(tree.surface)
    h = surface_grid_mm(tree, voxel_mm)
    sdf, origin = lumen_sdf_grid(tree, h)
    return polish(iso_surface(sdf, origin, np.full(3, h), 0.0), max_triangles=max_triangles)


def surface_grid_mm(tree: AirwayTree, voxel_mm: float = 0.5) -> float:
    """The contouring grid spacing ``lumen_surface`` uses for ``tree``."""
    r_min = min(float(b.radii.min()) for b in tree.branches)
    return float(np.clip(r_min / RADIUS_VOXELS, voxel_mm, max(COARSEST_MM, voxel_mm)))


def iso_surface(values: np.ndarray, origin: np.ndarray, spacing: np.ndarray, level: float):
    """Flying Edges iso-surface of a ``[z, y, x]`` array (VTK's x-fastest layout)."""


    image = image_from_array(values, origin, spacing)
    fe = vtkFlyingEdges3D()
    fe.SetInputData(image)
    fe.SetValue(0, float(level))
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    fe.Update()
    return fe.GetOutput()


def polish(poly, *, max_triangles: int | None = MAX_TRIANGLES, smooth: bool = True):
    """Largest piece, windowed-sinc smoothing, decimation to ``max_triangles``, normals into the lumen."""
    poly = largest_piece(poly)
    if smooth:
        poly = _smooth(poly)
    n = poly.GetNumberOfPolys()
    if max_triangles is not None and n > max_triangles:
        poly = _decimated_closed(poly, min(MAX_REDUCTION, 1.0 - max_triangles / n))
    return clean_surface(poly)


def _decimated_closed(poly, reduction: float):
    """Quadric decimation (smooth result), else topology-preserving DecimatePro, else none:
    the first that leaves the surface closed and manifold."""
    for decimate in (_decimate_quadric, _decimate_pro):
        reduced = _drop_fins(decimate(poly, reduction))
        report = mesh_report(reduced, pieces=False)
        if report["boundary_edges"] == 0 and report["non_manifold_edges"] == 0:
            return reduced
    warnings.warn(f"decimation opened the surface; kept all {poly.GetNumberOfPolys()} triangles", stacklevel=3)
    return poly


def _smooth(poly):

    sinc = vtkWindowedSincPolyDataFilter()
    sinc.SetInputData(poly)
    sinc.SetNumberOfIterations(SMOOTH_ITERATIONS)
    sinc.SetPassBand(SMOOTH_PASSBAND)
    sinc.BoundarySmoothingOff()
    sinc.FeatureEdgeSmoothingOff()
    sinc.NonManifoldSmoothingOn()
    sinc.NormalizeCoordinatesOn()
    sinc.Update()
    return sinc.GetOutput()


def _decimate_quadric(poly, reduction: float):

    dec = vtkQuadricDecimation()  # keeps the shape smooth (DecimatePro leaves visible creases)
    dec.SetInputData(poly)
    dec.SetTargetReduction(float(reduction))
    dec.VolumePreservationOn()
    dec.Update()
    return dec.GetOutput()


def _decimate_pro(poly, reduction: float):

    dec = vtkDecimatePro()  # topology-preserving: the surface stays closed and manifold
    dec.SetInputData(poly)
    dec.SetTargetReduction(float(reduction))
    dec.PreserveTopologyOn()
    dec.SplittingOff()
    dec.BoundaryVertexDeletionOff()
    dec.Update()
    return dec.GetOutput()


def _drop_fins(poly):
    """Remove back-to-back duplicate triangles (a collapsed pocket decimation sometimes leaves).

    Such a pair shares all three edges, so one of them ends up on four triangles (a
    non-manifold edge); dropping both copies leaves the rest of the surface closed.
    """

    points, tris = polydata_to_arrays(poly)
    _, inverse, counts = np.unique(np.sort(tris, axis=1), axis=0, return_inverse=True, return_counts=True)
    dup = counts[inverse.ravel()] > 1
    return polydata_from_arrays(points, tris[~dup]) if dup.any() else poly


def largest_piece(poly):
    """The largest connected piece of a surface (a new vtkPolyData without unused points)."""

    conn = vtkPolyDataConnectivityFilter()
    conn.SetInputData(poly)
    conn.SetExtractionModeToLargestRegion()
    clean = vtkCleanPolyData()  # the connectivity filter leaves the other pieces' points behind
    clean.SetInputConnection(conn.GetOutputPort())
    clean.PointMergingOff()
    clean.Update()
    return clean.GetOutput()


def clean_surface(poly):
    """Triangulated, merged, largest connected piece, normals into the lumen (a new vtkPolyData)."""

    tri = vtkTriangleFilter()
    tri.SetInputData(poly)
    tri.PassLinesOff()
    tri.PassVertsOff()
    clean = vtkCleanPolyData()
    clean.SetInputConnection(tri.GetOutputPort())
    clean.Update()
    normals = vtkPolyDataNormals()
    normals.SetInputData(largest_piece(clean.GetOutput()))
    normals.ComputePointNormalsOn()
    normals.ComputeCellNormalsOff()
    normals.SplittingOff()
    normals.ConsistencyOn()
    normals.AutoOrientNormalsOn()  # outward on a closed surface ...
    normals.FlipNormalsOn()  # ... then flipped: the camera looks at the wall from inside
    normals.Update()
    out = normals.GetOutput()
    result = type(out)()
    result.DeepCopy(out)
    return result


def surface_from_mask(mask: np.ndarray, spacing_xyz: np.ndarray, origin_xyz: np.ndarray, *,
                      max_triangles: int | None = MAX_TRIANGLES):
    """Lumen surface (mm) of a binary ``[z, y, x]`` mask: slight blur, Flying Edges at 0.5, polish."""
    pad = 2
    mask = np.pad(np.asarray(mask, dtype=np.float32), pad)
    blurred = ndimage.gaussian_filter(mask, sigma=0.6)  # removes voxel stair-steps before the iso-surface
    origin = np.asarray(origin_xyz, dtype=np.float64) - pad * np.asarray(spacing_xyz, dtype=np.float64)
    return polish(iso_surface(blurred.astype(np.float32), origin, np.asarray(spacing_xyz), 0.5), max_triangles=max_triangles)


def mesh_report(poly, pieces: bool = True) -> dict[str, int]:
    """Counts for checking a surface: triangles, boundary edges, non-manifold edges, connected pieces."""

    edges = {}
    for kind in ("boundary", "non_manifold"):
        fe = vtkFeatureEdges()
        fe.SetInputData(poly)
        fe.FeatureEdgesOff()
        fe.ManifoldEdgesOff()
        fe.SetBoundaryEdges(kind == "boundary")
        fe.SetNonManifoldEdges(kind == "non_manifold")
        fe.Update()
        edges[kind] = fe.GetOutput().GetNumberOfCells()
    report = {"triangles": poly.GetNumberOfPolys(), "boundary_edges": edges["boundary"],
              "non_manifold_edges": edges["non_manifold"]}
    if pieces:
        conn = vtkPolyDataConnectivityFilter()
        conn.SetInputData(poly)
        conn.SetExtractionModeToAllRegions()
        conn.Update()
        report["pieces"] = conn.GetNumberOfExtractedRegions()
    return report
