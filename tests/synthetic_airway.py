"""A small hand-built airway tree (7 branches) and writers for anatomy tests: graphs, volumes, meshes."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from bronchocli.anatomy import AirwayTree, Branch

# (start, end, radius, parent): trachea, right main (short, steep, wide), left main, then
# an upper (rising laterally) and a lower (descending) lobar bronchus on each side.
_SPEC = [
    ((0, 0, 60), (0, 0, 30), 4.0, None),
    ((0, 0, 30), (-8, 0, 17), 3.2, 0),
    ((0, 0, 30), (17, 0, 16), 2.8, 0),
    ((-8, 0, 17), (-22, 0, 22), 2.2, 1),
    ((-8, 0, 17), (-13, 0, 0), 2.4, 1),
    ((17, 0, 16), (30, 0, 22), 2.0, 2),
    ((17, 0, 16), (22, 0, -1), 2.2, 2),
]


def synthetic_tree(step_mm: float = 0.5) -> AirwayTree:
    branches = []
    for start, end, radius, parent in _SPEC:
        a, b = np.asarray(start, float), np.asarray(end, float)
        n = max(int(np.ceil(np.linalg.norm(b - a) / step_mm)), 2)
        t = np.linspace(0, 1, n + 1)[:, None]
        gen = 0 if parent is None else branches[parent].generation + 1
        branches.append(Branch(points=a + t * (b - a), radii=np.full(n + 1, radius), parent=parent, generation=gen))
        if parent is not None:
            branches[parent].children.append(len(branches) - 1)
    return AirwayTree(branches=branches, origin_mm=np.full(3, -40.0), spacing_mm=np.full(3, 0.5), name="synthetic")


def synthetic_mask(voxel_mm: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    """(mask [z, y, x] uint8, origin xyz) of the synthetic tree's lumen."""
    from bronchocli.anatomy.sdf import lumen_sdf_grid

    sdf, origin = lumen_sdf_grid(synthetic_tree(), voxel_mm)
    return (sdf < 0).astype(np.uint8), origin


def write_volume(path: Path, mask: np.ndarray, origin: np.ndarray, spacing: float) -> Path:
    """Write a label volume with VTK (.nii/.nii.gz/.mhd) or by hand (.nrrd: VTK has no NRRD writer)."""
    name = path.name.lower()
    if name.endswith(".nrrd"):
        nz, ny, nx = mask.shape
        header = ("NRRD0004\ntype: uint8\ndimension: 3\nspace: left-posterior-superior\n"
                  f"sizes: {nx} {ny} {nz}\nspace directions: ({spacing},0,0) (0,{spacing},0) (0,0,{spacing})\n"
                  f"kinds: domain domain domain\nencoding: raw\nendian: little\n"
                  f"space origin: ({origin[0]},{origin[1]},{origin[2]})\n\n")
        path.write_bytes(header.encode() + np.ascontiguousarray(mask, dtype=np.uint8).tobytes())
        return path
    from vtkmodules.vtkIOImage import vtkMetaImageWriter, vtkNIFTIImageWriter

    from bronchocli.anatomy._vtk import image_from_array

    image = image_from_array(np.ascontiguousarray(mask, dtype=np.uint8), origin, np.full(3, spacing))
    writer = vtkMetaImageWriter() if name.endswith(".mhd") else vtkNIFTIImageWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(image)
    writer.Write()
    return path


def write_mesh(path: Path, poly) -> Path:
    from vtkmodules.vtkIOGeometry import vtkOBJWriter, vtkSTLWriter
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    ext = path.suffix.lower()
    writer = {".stl": vtkSTLWriter, ".obj": vtkOBJWriter, ".vtp": vtkXMLPolyDataWriter}[ext]()
    writer.SetFileName(str(path))
    writer.SetInputData(poly)
    writer.Write()
    return path


def write_graph(path: Path, points: np.ndarray, edges: np.ndarray, point_arrays: dict | None = None) -> Path:
    """Write line cells (one per edge) as .vtu (unstructured grid) or .vtp (poly data) with point arrays."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import VTK_LINE, vtkCellArray, vtkPolyData, vtkUnstructuredGrid
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter, vtkXMLUnstructuredGridWriter

    vpts = vtkPoints()
    vpts.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    cells = vtkCellArray()
    for a, b in np.asarray(edges).tolist():
        cells.InsertNextCell(2, [a, b])
    if path.suffix == ".vtu":
        data, writer = vtkUnstructuredGrid(), vtkXMLUnstructuredGridWriter()
        data.SetPoints(vpts)
        data.SetCells(VTK_LINE, cells)
    else:
        data, writer = vtkPolyData(), vtkXMLPolyDataWriter()
        data.SetPoints(vpts)
        data.SetLines(cells)
    for name, values in (point_arrays or {}).items():
        arr = numpy_to_vtk(np.ascontiguousarray(values, dtype=np.float64), deep=True)
        arr.SetName(name)
        data.GetPointData().AddArray(arr)
    writer.SetFileName(str(path))
    writer.SetInputData(data)
    writer.Write()
    return path


def tree_graph(tree) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points, radii, edges) of a tree as one graph with shared junction points."""
    points, radii, edges, index = [], [], [], {}
    def node(p, r):
        key = tuple(np.round(p, 6))
        if key not in index:
            index[key] = len(points)
            points.append(p)
            radii.append(r)
        return index[key]
    for b in tree.branches:
        ids = [node(p, r) for p, r in zip(b.points, b.radii)]
        edges += list(itertools.pairwise(ids))
    return np.asarray(points), np.asarray(radii), np.asarray(edges)
