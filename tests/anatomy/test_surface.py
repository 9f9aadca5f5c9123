"""The lumen surface: closed, manifold, one piece, centreline inside, wall at the radius, normals inward."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from synthetic_airway import synthetic_tree

from bronchocli.anatomy import load_anatomy, lumen_surface
from bronchocli.anatomy._vtk import points_of
from bronchocli.anatomy.lumen import Lumen
from bronchocli.anatomy.sdf import lumen_sdf_grid, round_cone_distance
from bronchocli.anatomy.surface import MAX_TRIANGLES, mesh_report, surface_grid_mm


def enclosed(surface, points: np.ndarray) -> np.ndarray:
    """Inside test by VTK's ray casting (independent of our distance code)."""
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkPolyData
    from vtkmodules.vtkFiltersModeling import vtkSelectEnclosedPoints

    pts = vtkPoints()
    for p in points:
        pts.InsertNextPoint(*p)
    data = vtkPolyData()
    data.SetPoints(pts)
    sel = vtkSelectEnclosedPoints()
    sel.SetInputData(data)
    sel.SetSurfaceData(surface)
    sel.CheckSurfaceOn()
    sel.Update()
    return np.array([sel.IsInside(i) for i in range(len(points))], dtype=bool)


def centreline_sample(tree, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    pts = np.concatenate([b.points for b in tree.branches])
    rad = np.concatenate([b.radii for b in tree.branches])
    idx = np.random.default_rng(seed).choice(len(pts), size=min(n, len(pts)), replace=False)
    return pts[idx], rad[idx]


def assert_closed_one_piece(surface):
    report = mesh_report(surface)
    assert report == {**report, "boundary_edges": 0, "non_manifold_edges": 0, "pieces": 1}
    return report


def test_synthetic_surface_geometry():
    tree = synthetic_tree()
    surface = lumen_surface(tree, 0.5, max_triangles=None)
    assert_closed_one_piece(surface)
    pts, _ = centreline_sample(tree, 60)
    assert enclosed(surface, pts).all()
    # 1.5 mm beyond the wall, sideways from the trachea and the lower-right lobar bronchus: outside
    outside = np.array([[5.5, 0, 45], [0, -5.5, 40], [-7.6, 0, 4.6]])
    assert not enclosed(surface, outside).any()
    # every vertex sits on the wall: distance to the centreline = local radius (smoothing shrinks a little)
    verts = points_of(surface)
    dist, radius = Lumen(tree).nearest(verts)[:2]
    err = dist - radius
    assert np.median(np.abs(err)) < 0.1 and np.percentile(np.abs(err), 95) < 0.35
    # normals point into the lumen, towards the nearest centreline point
    from bronchocli.anatomy._vtk import vtk_to_numpy

    normals = vtk_to_numpy(surface.GetPointData().GetNormals())
    towards = Lumen(tree).nearest(verts).point_mm - verts
    assert np.mean(np.einsum("ij,ij->i", normals, towards) > 0) > 0.99


@pytest.mark.parametrize("seed", [0, 3])
def test_procedural_surface(seed):
    tree = load_anatomy("procedural", seed=seed)
    surface = lumen_surface(tree)
    report = assert_closed_one_piece(surface)
    assert report["triangles"] <= MAX_TRIANGLES
    pts, _ = centreline_sample(tree, 150, seed)
    assert enclosed(surface, pts).all()
    for p in tree.lobe_paths.values():
        assert enclosed(surface, p.points[:: max(len(p.points) // 40, 1)]).all()


def test_real_tree_surface_is_one_piece(real_tree):
    tree = load_anatomy(real_tree)
    assert surface_grid_mm(tree, 0.5) == 0.5  # sub-mm airways: contoured at the finest grid
    surface = lumen_surface(tree, 0.5)
    assert_closed_one_piece(surface)
    pts, _ = centreline_sample(tree, 150)
    assert enclosed(surface, pts).all()


def test_thin_airways_stay_connected():
    tree = synthetic_tree()
    for b in tree.branches[3:]:
        b.radii[:] = 0.2  # far below one voxel: drawn at the one-voxel minimum radius
    surface = lumen_surface(tree, 1.0, max_triangles=None)
    assert_closed_one_piece(surface)
    ends = np.array([b.points[-1] - 0.5 * (b.points[-1] - b.points[0]) for b in tree.branches[3:]])
    assert enclosed(surface, ends).all()


def test_own_surface_is_returned(tmp_path):
    from synthetic_airway import synthetic_mask, write_volume

    mask, origin = synthetic_mask(0.6)
    tree = load_anatomy(write_volume(tmp_path / "v.mhd", mask, origin, 0.6))
    surface = lumen_surface(tree)
    assert surface is not tree.surface
    assert surface.GetNumberOfPolys() == tree.surface.GetNumberOfPolys()
    back = pickle.loads(pickle.dumps(tree))  # workers receive trees by pickle: the surface travels as arrays
    assert back.surface.GetNumberOfPolys() == tree.surface.GetNumberOfPolys()
    np.testing.assert_allclose(points_of(back.surface), points_of(tree.surface))


def test_sdf_grid_matches_brute_force():
    tree = synthetic_tree()
    sdf, origin = lumen_sdf_grid(tree, 1.0)
    rng = np.random.default_rng(0)
    idx = np.stack([rng.integers(0, n, 300) for n in sdf.shape], axis=1)  # z, y, x
    xyz = origin + idx[:, ::-1] * 1.0
    # union of dense spheres along each branch: an independent (approximate) distance
    centres = np.concatenate([b.points for b in tree.branches])
    radii = np.concatenate([b.radii for b in tree.branches])
    brute = (np.linalg.norm(xyz[:, None] - centres[None], axis=2) - radii[None]).min(axis=1)
    got = sdf[tuple(idx.T)]
    near = np.abs(brute) < 2.0  # inside the narrow band the distance is exact
    assert np.all((got < 0) == (brute < 0))
    np.testing.assert_allclose(got[near & (brute > 0)], brute[near & (brute > 0)], atol=0.02)


def test_round_cone_distance_simple_cases():
    ba = np.array([0.0, 0.0, 10.0])
    p = np.array([[3.0, 0, 5], [0, 0, -2], [0, 0, 14], [0, 0, 5]], dtype=np.float32)
    d = round_cone_distance(*p.T, ba, 1.0, 1.0)  # a capsule of radius 1
    np.testing.assert_allclose(d, [2.0, 1.0, 3.0, -1.0], atol=1e-5)
    d = round_cone_distance(*np.array([[0, 0, -3.0]], dtype=np.float32).T, ba, 2.0, 1.0)
    np.testing.assert_allclose(d, [1.0], atol=1e-5)  # beyond the wide end: distance to its sphere
