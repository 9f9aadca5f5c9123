"""numpy <-> VTK conversions and VTK error capture shared by the anatomy package.

The anatomy package is used by dataset generation only; training, sweeps and
reports never import it, so they run where VTK is not installed.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

# Offscreen rendering needs EGL; harmless for the filters used here, but it must be
# set before the first VTK import anywhere in the process.
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

from vtkmodules.util.numpy_support import (  # noqa: E402
    numpy_to_vtk,
    numpy_to_vtkIdTypeArray,
    vtk_to_numpy,
)
from vtkmodules.vtkCommonCore import (  # noqa: E402
    vtkLogger,
    vtkOutputWindow,
    vtkPoints,
    vtkStringOutputWindow,
)
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkImageData, vtkPolyData  # noqa: E402

__all__ = [
    "captured_vtk_errors",
    "image_from_array",
    "image_to_array",
    "numpy_to_vtk",
    "numpy_to_vtkIdTypeArray",
    "points_of",
    "poly_from_state",
    "poly_state",
    "polydata_from_arrays",
    "polydata_to_arrays",
    "triangles_of",
    "vtk_to_numpy",
]


def points_of(data) -> np.ndarray:
    """(N, 3) float64 copy of a VTK data set's points."""
    pts = data.GetPoints()
    if pts is None:
        return np.zeros((0, 3))
    return vtk_to_numpy(pts.GetData()).astype(np.float64)


def triangles_of(poly: vtkPolyData) -> np.ndarray:
    """(T, 3) vertex indices of a triangulated vtkPolyData's polygons."""
    polys = poly.GetPolys()
    conn = vtk_to_numpy(polys.GetConnectivityArray())
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    if len(offsets) > 1 and np.any(np.diff(offsets) != 3):
        raise ValueError("surface is not triangulated")
    return conn.reshape(-1, 3).astype(np.int64)


def polydata_from_arrays(points: np.ndarray, triangles: np.ndarray) -> vtkPolyData:
    """A triangle vtkPolyData from (N, 3) points and (T, 3) vertex indices (copied)."""
    poly = vtkPolyData()
    vpts = vtkPoints()
    vpts.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    poly.SetPoints(vpts)
    tris = np.ascontiguousarray(triangles, dtype=np.int64)
    cells = vtkCellArray()
    offsets = np.arange(0, 3 * len(tris) + 1, 3, dtype=np.int64)
    cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True), numpy_to_vtkIdTypeArray(tris.ravel(), deep=True))
    poly.SetPolys(cells)
    return poly


def polydata_to_arrays(poly: vtkPolyData) -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of a triangle vtkPolyData; the inverse of ``polydata_from_arrays``."""
    return points_of(poly), triangles_of(poly)


def poly_state(poly: vtkPolyData) -> dict[str, np.ndarray]:
    """A triangle surface as plain arrays (points, triangles, point normals if any), for pickling."""
    state = {"points": points_of(poly), "triangles": triangles_of(poly)}
    normals = poly.GetPointData().GetNormals()
    if normals is not None:
        state["normals"] = vtk_to_numpy(normals).copy()
    return state


def poly_from_state(state: dict[str, np.ndarray]) -> vtkPolyData:
    poly = polydata_from_arrays(state["points"], state["triangles"])
    if "normals" in state:
        normals = numpy_to_vtk(np.ascontiguousarray(state["normals"]), deep=True)
        normals.SetName("Normals")
        poly.GetPointData().SetNormals(normals)
    return poly


def image_from_array(values: np.ndarray, origin: np.ndarray, spacing: np.ndarray) -> vtkImageData:
    """vtkImageData over a numpy volume indexed ``[z, y, x]`` (VTK's x-fastest order), sharing memory.

    The array is kept alive on the returned object, because VTK does not own it.
    """
    values = np.ascontiguousarray(values)
    image = vtkImageData()
    nz, ny, nx = values.shape
    image.SetDimensions(nx, ny, nz)
    image.SetOrigin(*map(float, origin))
    image.SetSpacing(*map(float, spacing))
    scalars = numpy_to_vtk(values.ravel(), deep=False)
    scalars.SetName("values")
    image.GetPointData().SetScalars(scalars)
    image._numpy_keepalive = values  # noqa: SLF001 (VTK holds a raw pointer into this buffer)
    return image


def image_to_array(image: vtkImageData) -> np.ndarray:
    """A vtkImageData's first scalar component as a numpy array indexed ``[z, y, x]``."""
    nx, ny, nz = image.GetDimensions()
    scalars = image.GetPointData().GetScalars()
    if scalars is None:
        raise ValueError("image has no scalars")
    values = vtk_to_numpy(scalars)
    if values.ndim == 2:
        values = values[:, 0]
    return values.reshape(nz, ny, nx)



@contextmanager
def captured_vtk_errors() -> Iterator[list[str]]:
    """Silence VTK's error and warning output (readers of bad files are noisy); yields a list that
    holds one line per error message, object addresses stripped, once the block has run."""
    previous = vtkOutputWindow.GetInstance()
    verbosity = vtkLogger.GetCurrentVerbosityCutoff()
    window = vtkStringOutputWindow()
    vtkOutputWindow.SetInstance(window)
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    messages: list[str] = []
    try:
        yield messages
    finally:
        vtkOutputWindow.SetInstance(previous)
        vtkLogger.SetStderrVerbosity(verbosity)
        for block in re.split(r"\n\s*\n", window.GetOutput()):
            lines = [ln.strip() for ln in block.splitlines() if ln.strip()]
            if len(lines) >= 2 and lines[0].startswith("ERROR"):  # warnings are dropped
                messages.append(re.sub(r" \(0x[0-9a-f]+\)", "", lines[1]))
