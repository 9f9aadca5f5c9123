"""Anatomy files -> AirwayTree: centreline graphs, segmentation volumes and surface meshes.

Extension -> reader (``READERS``); a ``.vtp`` is a centreline graph when it has
line cells and a radius array, otherwise a surface mesh. Volumes keep the file's
voxel grid (origin, spacing); graphs and meshes get an isotropic ``voxel_mm`` grid
around the airway. Volume and mesh trees carry their own lumen surface
(``tree.surface``).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkFiltersCore import vtkCellDataToPointData
from vtkmodules.vtkImagingStencil import (
    vtkImageStencilToImage,
    vtkPolyDataToImageStencil,
)
from vtkmodules.vtkIOGeometry import vtkOBJReader, vtkSTLReader
from vtkmodules.vtkIOImage import vtkMetaImageReader, vtkNIFTIImageReader, vtkNrrdReader
from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLUnstructuredGridReader

from ..errors import DataError
from ..io import write_polydata
from ._vtk import (
    captured_vtk_errors,
    image_to_array,
    numpy_to_vtk,
    numpy_to_vtkIdTypeArray,
    points_of,
    vtk_to_numpy,
)
from .airway import AirwayTree
from .graph import tree_from_graph
from .skeleton import graph_from_mask, largest_component
from .surface import clean_surface, polish, surface_from_mask

GRAPH_EXTS = (".vtu", ".vtp")
SKELETON_SMOOTH_MM = 1.0  # skeleton centrelines step between voxels: smooth their points this much
RADIUS_NAMES = ("radius", "radii", "maximuminscribedsphereradius")  # lower case; VMTK uses the last


def extension(path: str | Path) -> str:
    name = Path(path).name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else Path(name).suffix


def read_anatomy_file(path: str | Path, *, voxel_mm: float = 0.5,
                      centreline: str | Path | None = None) -> AirwayTree:
    """The airway tree in ``path`` (any of ``ALLOWED_EXTS``); ``centreline`` serves volumes and meshes."""
    path = Path(path)
    ext = extension(path)
    if ext not in ALLOWED_EXTS:
        raise DataError(f"{path}: unknown anatomy file type '{ext or path.name}'; allowed: 'procedural' or a file "
                        f"ending in {', '.join(ALLOWED_EXTS)}")
    if not path.is_file():
        raise DataError(f"{path}: anatomy file not found")
    return READERS[ext](path, voxel_mm, centreline)


# ---- centreline graphs --------------------------------------------------------------------
def _read_xml(path: Path):

    reader = vtkXMLUnstructuredGridReader() if extension(path) == ".vtu" else vtkXMLPolyDataReader()
    data = _run(reader, path)
    if data is None or data.GetNumberOfPoints() == 0:
        raise DataError(f"{path}: could not read any points (not a VTK XML {extension(path)} file, or empty)")
    return data


def _run(reader, path: Path):
    """Run a VTK reader on ``path``; its error messages become one DataError line instead of log spam."""

    reader.SetFileName(str(path))
    with captured_vtk_errors() as errors:
        reader.Update()
    if errors:
        raise DataError(f"{path}: could not read it as a {extension(path)} file ({errors[0]})")
    return reader.GetOutput()


def _line_edges(data) -> np.ndarray:
    """(E, 2) point pairs of the line and polyline cells of a vtkPolyData or vtkUnstructuredGrid."""

    if data.IsA("vtkPolyData"):
        cells = data.GetLines()
        keep = None
    else:
        cells = data.GetCells()
        keep = np.isin(_cell_types(data), (3, 4))  # VTK_LINE, VTK_POLY_LINE
    if cells is None or cells.GetNumberOfCells() == 0:
        return np.zeros((0, 2), dtype=np.int64)
    offsets = vtk_to_numpy(cells.GetOffsetsArray()).astype(np.int64)
    conn = vtk_to_numpy(cells.GetConnectivityArray()).astype(np.int64)
    cell_of = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    j = np.arange(len(conn) - 1)
    same = cell_of[j] == cell_of[j + 1]
    if keep is not None:
        same &= keep[cell_of[j]]
    return np.stack([conn[j[same]], conn[j[same] + 1]], axis=1)


def _cell_types(grid) -> np.ndarray:

    try:
        types = grid.GetCellTypes()  # VTK >= 9.6: the per-cell type array
    except TypeError:
        types = grid.GetCellTypesArray()  # older VTK
    return vtk_to_numpy(types)


def _radius_array(data, path: Path) -> np.ndarray:
    """Per-point lumen radii (mm) from a radius-like (or diameter) point or cell array."""


    found = _find_radius(data.GetPointData())
    if found is None and _find_radius(data.GetCellData()) is not None:
        c2p = vtkCellDataToPointData()
        c2p.SetInputData(data)
        c2p.Update()
        found = _find_radius(c2p.GetOutput().GetPointData())
    if found is None:
        names = [data.GetPointData().GetArrayName(i) for i in range(data.GetPointData().GetNumberOfArrays())]
        names += [data.GetCellData().GetArrayName(i) for i in range(data.GetCellData().GetNumberOfArrays())]
        raise DataError(f"{path}: the centreline graph has no radius array (a point or cell array named "
                        f"'radius', '*radius*' or 'diameter'); arrays present: {', '.join(map(str, names)) or 'none'}")
    array, scale = found
    values = vtk_to_numpy(array).astype(np.float64)
    return (values if values.ndim == 1 else values[:, 0]) * scale


def _find_radius(arrays):
    names = {arrays.GetArrayName(i): arrays.GetArray(i) for i in range(arrays.GetNumberOfArrays())}
    lower = {str(k).lower(): v for k, v in names.items() if v is not None}
    for name in RADIUS_NAMES:
        if name in lower:
            return lower[name], 1.0
    for name, arr in lower.items():
        if "radius" in name:
            return arr, 1.0
    for name, arr in lower.items():
        if "diameter" in name:
            return arr, 0.5
    return None


def _is_graph(data) -> bool:
    return len(_line_edges(data)) > 0 and (data.GetNumberOfPolys() == 0 if data.IsA("vtkPolyData") else True)


def graph_arrays(path: Path, data=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points, radii, edges) of a .vtu/.vtp centreline graph (``data``: the file, already read)."""

    data = _read_xml(path) if data is None else data
    edges = _line_edges(data)
    if len(edges) == 0:
        raise DataError(f"{path}: no line or polyline cells; a centreline graph needs them")
    return points_of(data), _radius_array(data, path), edges


def _from_graph_file(path: Path, voxel_mm: float, centreline, data=None) -> AirwayTree:
    points, radii, edges = graph_arrays(path, data)
    return tree_from_graph(points, radii, edges, name=path.name, source=str(path), voxel_mm=voxel_mm)


def _from_vtp(path: Path, voxel_mm: float, centreline) -> AirwayTree:
    data = _read_xml(path)
    if _is_graph(data):
        return _from_graph_file(path, voxel_mm, centreline, data)
    if data.GetNumberOfPolys() == 0:
        raise DataError(f"{path}: neither a centreline graph (line cells + radius array) nor a surface (polygons)")
    return _tree_from_surface(data, path, voxel_mm, centreline)


# ---- segmentation volumes ------------------------------------------------------------------
def read_volume(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(foreground mask [z, y, x], spacing xyz, origin xyz) of a label volume: nonzero = airway."""


    ext = extension(path)
    if ext == ".mhd":
        _check_metaimage_header(path)  # MetaIO prints parse failures itself, past VTK's error handling
    reader = {".nii": vtkNIFTIImageReader, ".nii.gz": vtkNIFTIImageReader,
              ".mhd": vtkMetaImageReader, ".nrrd": vtkNrrdReader}[ext]()
    image = _run(reader, path)
    dims = image.GetDimensions()
    if image.GetPointData().GetScalars() is None or np.prod(dims) == 0:
        raise DataError(f"{path}: could not read a volume (not a valid {ext} file?)")
    if image.GetNumberOfScalarComponents() != 1:
        raise DataError(f"{path}: volume has {image.GetNumberOfScalarComponents()} components per voxel; "
                        "expected a single-component label map")
    if ext == ".nrrd":
        _check_nrrd_size(path, image)
    origin = np.asarray(image.GetOrigin(), dtype=np.float64)
    if ext in (".nii", ".nii.gz"):
        origin = _nifti_origin(reader, origin)
    return image_to_array(image) > 0, np.asarray(image.GetSpacing(), dtype=np.float64), origin


def _check_metaimage_header(path: Path) -> None:
    head = path.read_bytes()[:8192].decode("latin-1")
    if not all(re.search(rf"^\s*{key}\s*=", head, re.MULTILINE) for key in ("NDims", "ElementDataFile")):
        raise DataError(f"{path}: not a MetaImage header (needs NDims = ... and ElementDataFile = ... lines)")
    data = re.search(r"^\s*ElementDataFile\s*=\s*(\S+)", head, re.MULTILINE).group(1)
    if data not in ("LOCAL", "LIST") and "%" not in data and not (path.parent / data).is_file():
        raise DataError(f"{path}: its data file {data} is missing (expected beside the header)")


def _check_nrrd_size(path: Path, image) -> None:
    """VTK's NRRD reader does not notice a truncated raw file (it returns garbage): check the size."""
    raw = path.read_bytes()
    end = raw.find(b"\n\n")
    header = raw[:end].decode("latin-1") if end > 0 else ""
    if re.search(r"^data ?file:", header, re.MULTILINE) or not re.search(r"^encoding:\s*raw", header, re.MULTILINE):
        return
    expected = int(np.prod(image.GetDimensions())) * image.GetScalarSize() * image.GetNumberOfScalarComponents()
    if len(raw) - (end + 2) < expected:
        raise DataError(f"{path}: truncated: {len(raw) - end - 2} data bytes for {expected} expected")


def _nifti_origin(reader, origin: np.ndarray) -> np.ndarray:
    """VTK's NIfTI reader reports origin 0 and keeps the offset in the q/s-form; use it when unrotated."""
    for get in (reader.GetQFormMatrix, reader.GetSFormMatrix):
        m = get()
        if m is None:
            continue
        rot = np.array([[m.GetElement(i, j) for j in range(3)] for i in range(3)])
        if np.allclose(rot, np.eye(3), atol=1e-6):
            return np.array([m.GetElement(i, 3) for i in range(3)])
        return origin  # rotated or flipped axes: stay in the voxel grid's own frame (documented)
    return origin


def _from_volume(path: Path, voxel_mm: float, centreline) -> AirwayTree:

    mask, spacing, origin = read_volume(path)
    mask = largest_component(mask, str(path))
    nonzero = np.nonzero(mask.any(axis=(1, 2))), np.nonzero(mask.any(axis=(0, 2))), np.nonzero(mask.any(axis=(0, 1)))
    lo = np.array([ax[0].min() for ax in nonzero])
    hi = np.array([ax[0].max() + 1 for ax in nonzero])
    crop = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    crop_origin = origin + lo[::-1] * spacing
    if centreline is not None:
        tree = _centreline_tree(Path(centreline), voxel_mm, grid=(spacing, origin))
    else:
        points, radii, edges = graph_from_mask(crop, spacing, crop_origin, str(path))
        tree = tree_from_graph(points, radii, edges, name=path.name, source=str(path), origin_mm=origin,
                               spacing_mm=spacing, smooth_points_mm=SKELETON_SMOOTH_MM)
    tree.name = path.name
    tree.surface = surface_from_mask(crop, spacing, crop_origin)
    return tree


# ---- surface meshes ------------------------------------------------------------------------
def _read_mesh(path: Path):

    reader = {".stl": vtkSTLReader, ".obj": vtkOBJReader}[extension(path)]()
    return _run(reader, path)


def _from_mesh(path: Path, voxel_mm: float, centreline) -> AirwayTree:
    return _tree_from_surface(_read_mesh(path), path, voxel_mm, centreline)


def _tree_from_surface(poly, path: Path, voxel_mm: float, centreline) -> AirwayTree:

    if poly is None or poly.GetNumberOfPolys() == 0:
        raise DataError(f"{path}: no surface polygons found (empty or unreadable {extension(path)} file)")
    surface = polish(clean_surface(poly), smooth=False)  # the user's shape, within the triangle budget
    if centreline is not None:
        tree = _centreline_tree(Path(centreline), voxel_mm)
        _check_inside_bounds(tree, surface, Path(centreline), path)
    else:
        mask, origin = voxelise(surface, voxel_mm)
        points, radii, edges = graph_from_mask(mask, np.full(3, voxel_mm), origin, str(path))
        tree = tree_from_graph(points, radii, edges, name=path.name, source=str(path), voxel_mm=voxel_mm,
                               smooth_points_mm=SKELETON_SMOOTH_MM)
    tree.name = path.name
    tree.surface = surface
    return tree


def _centreline_tree(path: Path, voxel_mm: float, grid: tuple | None = None) -> AirwayTree:
    if extension(path) not in GRAPH_EXTS:
        raise DataError(f"{path}: a centreline must be a .vtu or .vtp graph, not '{extension(path)}'")
    if not path.is_file():
        raise DataError(f"{path}: centreline file not found")
    points, radii, edges = graph_arrays(path)
    spacing, origin = grid if grid is not None else (None, None)
    return tree_from_graph(points, radii, edges, name=path.name, source=str(path), voxel_mm=voxel_mm,
                           origin_mm=origin, spacing_mm=spacing)


def _check_inside_bounds(tree: AirwayTree, surface, centreline: Path, mesh: Path) -> None:
    b = np.asarray(surface.GetBounds()).reshape(3, 2)
    pts = np.concatenate([br.points for br in tree.branches])
    slack = 0.1 * (b[:, 1] - b[:, 0])
    inside = np.all((pts >= b[:, 0] - slack) & (pts <= b[:, 1] + slack), axis=1)
    if inside.mean() < 0.9:
        raise DataError(f"{centreline}: {100 * (1 - inside.mean()):.0f}% of the centreline lies outside the "
                        f"bounds of {mesh}; both must be in the same coordinates (mm)")


def voxelise(surface, voxel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(mask [z, y, x], origin xyz) of the inside of a closed surface on a ``voxel_mm`` grid."""


    b = np.asarray(surface.GetBounds()).reshape(3, 2)
    origin = b[:, 0] - 2 * voxel_mm
    dims = np.ceil((b[:, 1] - b[:, 0]) / voxel_mm).astype(int) + 5
    stencil = vtkPolyDataToImageStencil()
    stencil.SetInputData(surface)
    stencil.SetOutputOrigin(*origin)
    stencil.SetOutputSpacing(voxel_mm, voxel_mm, voxel_mm)
    stencil.SetOutputWholeExtent(0, dims[0] - 1, 0, dims[1] - 1, 0, dims[2] - 1)
    image = vtkImageStencilToImage()
    image.SetInputConnection(stencil.GetOutputPort())
    image.SetInsideValue(1)
    image.SetOutsideValue(0)
    image.SetOutputScalarTypeToUnsignedChar()
    image.Update()
    return image_to_array(image.GetOutput()) > 0, origin


READERS: dict[str, Callable[[Path, float, object], AirwayTree]] = {
    ".vtu": _from_graph_file,
    ".vtp": _from_vtp,
    ".nii": _from_volume,
    ".nii.gz": _from_volume,
    ".mhd": _from_volume,
    ".nrrd": _from_volume,
    ".stl": _from_mesh,
    ".obj": _from_mesh,
}
ALLOWED_EXTS = tuple(READERS)  # what read_anatomy_file accepts: a new reader is one entry above


def save_centreline(tree: AirwayTree, path: str | Path) -> Path:
    """Write the tree as a .vtp centreline graph (one polyline per branch; point ``radius``;
    cell ``branch``, ``generation``, ``parent``), atomically. ``load_anatomy`` reads it back."""


    path = Path(path)
    pts = np.concatenate([b.points for b in tree.branches])
    sizes = np.array([len(b.points) for b in tree.branches])
    poly = vtkPolyData()
    vpts = vtkPoints()
    vpts.SetData(numpy_to_vtk(np.ascontiguousarray(pts, dtype=np.float64), deep=True))
    poly.SetPoints(vpts)
    lines = vtkCellArray()
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    lines.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_to_vtkIdTypeArray(np.arange(len(pts), dtype=np.int64), deep=True))
    poly.SetLines(lines)
    radius = numpy_to_vtk(np.concatenate([b.radii for b in tree.branches]).astype(np.float64), deep=True)
    radius.SetName("radius")
    poly.GetPointData().AddArray(radius)
    for name, values in (("branch", np.arange(len(tree.branches))),
                         ("generation", [b.generation for b in tree.branches]),
                         ("parent", [-1 if b.parent is None else b.parent for b in tree.branches])):
        arr = numpy_to_vtk(np.asarray(values, dtype=np.int32), deep=True)
        arr.SetName(name)
        poly.GetCellData().AddArray(arr)
    write_polydata(poly, path, "centreline")
    return path

