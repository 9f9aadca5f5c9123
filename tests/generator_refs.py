"""Independent references for the generator tests: a hand-made airway and from-scratch geometry.

Nothing here uses the anatomy package's or the generator's own geometry code:

* a bent tube: the centreline runs 60 mm straight down -z, then turns 90°
  towards +x on a 40 mm radius arc; the lumen radius tapers from 8 to 5 mm
  (``tube_tree``, ``tube_surface`` a capped vtkTubeFilter mesh);
* ``polyline_distance``: brute-force point-to-polyline distance with the radius
  interpolated at the closest point;
* ``reference_ups``: parallel transport with SciPy's shortest-arc alignment;
* ``arc_point``: a polyline point at an arc length, extrapolated past the end;
* ``check_ground_truth``: every frame of a generated dataset, read back from its CSV, against the above.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bronchocli.anatomy.airway import AirwayTree, Branch, LobePath


def tube_centreline(n_straight: int = 61, n_arc: int = 64) -> tuple[np.ndarray, np.ndarray]:
    straight = np.stack([np.zeros(n_straight), np.zeros(n_straight), np.linspace(0.0, -60.0, n_straight)], 1)
    theta = np.linspace(0.0, np.pi / 2, n_arc)[1:]
    arc = np.stack([40.0 - 40.0 * np.cos(theta), np.zeros_like(theta), -60.0 - 40.0 * np.sin(theta)], 1)
    points = np.concatenate([straight, arc])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    radii = 8.0 - 3.0 * s / s[-1]
    return points, radii


def tube_tree(spacing: float = 0.5) -> AirwayTree:
    points, radii = tube_centreline()
    tree = AirwayTree([Branch(points, radii, None)], origin_mm=points.min(0) - 10.0,
                      spacing_mm=np.full(3, spacing), name="tube")
    tree.lobe_paths = {lobe: LobePath(lobe, [0], points, radii) for lobe in ("ur", "br", "ul", "bl")}
    return tree


def tube_surface(sides: int = 48):
    import vtk

    points, radii = tube_centreline()
    pts = vtk.vtkPoints()
    for p in points:
        pts.InsertNextPoint(*p)
    line = vtk.vtkPolyLineSource()
    line.SetNumberOfPoints(len(points))
    for i, p in enumerate(points):
        line.SetPoint(i, *p)
    line.Update()
    poly = line.GetOutput()
    from vtkmodules.util.numpy_support import numpy_to_vtk

    r = numpy_to_vtk(radii.copy(), deep=True)
    r.SetName("radius")
    poly.GetPointData().SetScalars(r)
    tube = vtk.vtkTubeFilter()
    tube.SetInputData(poly)
    tube.SetVaryRadiusToVaryRadiusByAbsoluteScalar()
    tube.SetNumberOfSides(sides)
    tube.CappingOn()
    tri = vtk.vtkTriangleFilter()
    tri.SetInputConnection(tube.GetOutputPort())
    tri.Update()
    out = vtk.vtkPolyData()
    out.DeepCopy(tri.GetOutput())
    return out


def polyline_distance(points: np.ndarray, radii: np.ndarray, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance of each query point to the polyline and the radius interpolated at the closest point."""
    q = np.atleast_2d(np.asarray(query, dtype=np.float64))
    a, b = points[:-1], points[1:]
    ab = b - a
    t = np.clip(((q[:, None, :] - a) * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    closest = a + t[..., None] * ab
    d = np.linalg.norm(q[:, None, :] - closest, axis=-1)
    j = np.argmin(d, axis=1)
    rows = np.arange(len(q))
    tj = t[rows, j]
    return d[rows, j], radii[j] * (1 - tj) + radii[j + 1] * tj


def tube_distance(query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    points, radii = tube_centreline()
    return polyline_distance(points, radii, query)


def dedup(points: np.ndarray, *values: np.ndarray):
    """Drop consecutive repeated points (and the matching values)."""
    keep = np.concatenate([[True], np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-9])
    return (points[keep], *(v[keep] for v in values))


def reference_ups(points: np.ndarray) -> np.ndarray:
    """Up vector per segment: world -y (else +z) off the first direction, carried by shortest-arc rotations."""
    t = np.diff(points, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    up = np.array([0.0, -1.0, 0.0]) if abs(t[0, 1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    ups = [(up - up @ t[0] * t[0]) / np.linalg.norm(up - up @ t[0] * t[0])]
    for i in range(1, len(t)):
        rot, _ = Rotation.align_vectors(t[i][None], t[i - 1][None])
        ups.append(rot.apply(ups[-1]))
    return np.asarray(ups)


def arc_point(points: np.ndarray, arc: float, end_chord_mm: float = 2.0) -> tuple[np.ndarray, int]:
    """(point at arc length ``arc``, index of its segment); past the end, along the last ``end_chord_mm`` chord."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    if arc > s[-1]:
        back, _ = arc_point(points, s[-1] - end_chord_mm)
        t = (points[-1] - back) / np.linalg.norm(points[-1] - back)
        return points[-1] + (arc - s[-1]) * t, len(points) - 2
    i = int(min(np.searchsorted(s, arc, side="right") - 1, len(points) - 2))
    w = (arc - s[i]) / (s[i + 1] - s[i])
    return points[i] + w * (points[i + 1] - points[i]), i


def read_csv_rows(root: Path, patient: str) -> list[dict]:
    lines = (Path(root) / f"{patient}.csv").read_text().splitlines()
    head = lines[0].split(",")
    return [dict(zip(head, ln.split(","))) for ln in lines[1:]]


def read_graph(path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """Polylines (points mm, radii) of a saved centreline graph (.vtp)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    poly = reader.GetOutput()
    pts = vtk_to_numpy(poly.GetPoints().GetData()).astype(float)
    rad = vtk_to_numpy(poly.GetPointData().GetArray("radius")).astype(float)
    off = vtk_to_numpy(poly.GetLines().GetOffsetsArray())
    conn = vtk_to_numpy(poly.GetLines().GetConnectivityArray())
    return [(pts[conn[a:b]], rad[conn[a:b]]) for a, b in zip(off[:-1], off[1:]) if b - a > 1]


def check_ground_truth(root: Path, patient: str, tree) -> int:
    """Assert, for every frame of ``patient`` read back from its CSV, with geometry independent of the generator:

    * the camera (voxels -> mm via dataset.json) is inside the lumen: its distance to the nearest segment
      of the saved centreline graph is below the radius interpolated there;
    * it sits at the base point (``arc_mm`` on the lobe path) plus the recorded whole-voxel offset;
    * R·(1,0,0) points at the lobe-path point ``look_ahead_mm`` further on (extrapolated past the end);
    * the roll about the view axis, relative to the parallel-transported up, equals the ``roll`` column.

    ``tree`` supplies the lobe paths (the anatomy package's loader). Returns the number of frames checked.
    """
    import json

    from bronchocli import geometry

    meta = json.loads((Path(root) / "dataset.json").read_text())
    gen = meta["generator"]
    grid = meta["voxel_grid"][patient]
    origin, spacing = np.asarray(grid["origin_mm"]), np.asarray(grid["spacing_mm"])
    branches = read_graph(Path(root) / patient / "airway.vtp")
    paths = {lb: dedup(np.asarray(p.points, float))[0] for lb, p in tree.lobe_paths.items()}
    ups = {lb: reference_ups(p) for lb, p in paths.items()}
    rows = read_csv_rows(root, patient)
    for r in rows:
        where = r["filename"]
        pos = origin + spacing * np.array([float(r[k]) for k in ("pos_x", "pos_y", "pos_z")])
        R = geometry.euler_to_matrix(np.array([float(r[k]) for k in ("Rx", "Ry", "Rz")]))
        d, rad = min((polyline_distance(p, rr, pos[None]) for p, rr in branches), key=lambda dr: dr[0][0])
        assert d[0] < rad[0], f"{where}: camera outside the lumen ({d[0]:.2f} mm from the centreline, radius {rad[0]:.2f})"
        arc = float(r["arc_mm"])
        base, seg = arc_point(paths[r["lobe"]], arc)
        offset = np.array([int(r[k]) for k in ("dx", "dy", "dz")])
        assert np.abs(pos - (base + offset * spacing)).max() < 1e-4, f"{where}: not base point + offset"
        assert np.abs(offset).max() <= gen["offset_voxels"]
        assert r["base_filename"] == f"{r['lobe']}/b{round(arc / gen['base_step_mm']):05d}"
        look, _ = arc_point(paths[r["lobe"]], arc + gen["look_ahead_mm"])
        want = (look - pos) / np.linalg.norm(look - pos)
        angle = np.degrees(np.arccos(np.clip(R[:, 0] @ want, -1, 1)))
        assert angle < 1e-3, f"{where}: optical axis {angle:.4f}° off the look-at point"
        f, up = R[:, 0], ups[r["lobe"]][seg]
        ref_up = (up - (up @ f) * f) / np.linalg.norm(up - (up @ f) * f)
        roll = np.degrees(np.arctan2(f @ np.cross(ref_up, R[:, 2]), ref_up @ R[:, 2]))
        assert abs(roll - float(r["roll"])) < 1e-3, f"{where}: roll {roll:.4f}° but the CSV says {r['roll']}"
        assert abs(float(r["roll"]) / gen["roll_step_deg"] - round(float(r["roll"]) / gen["roll_step_deg"])) < 1e-9
    return len(rows)
