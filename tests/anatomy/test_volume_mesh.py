"""Segmentation volumes (.nii/.nii.gz/.mhd/.nrrd) and surface meshes (.stl/.obj/.vtp) -> airway trees."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_airway import synthetic_mask, synthetic_tree, tree_graph, write_graph, write_mesh, write_volume

from bronchocli.anatomy import load_anatomy, lumen_surface, main_bronchi
from bronchocli.anatomy.surface import mesh_report

VOXEL = 0.6
JUNCTIONS = np.array([[0.0, 0.0, 30.0], [-8.0, 0.0, 17.0], [17.0, 0.0, 16.0]])  # carina, right, left


@pytest.fixture(scope="module")
def mask_and_origin():
    return synthetic_mask(VOXEL)


@pytest.fixture(scope="module")
def mesh_surface():
    return lumen_surface(synthetic_tree(), 0.5)


def check_synthetic_tree(tree, radius_tol: float):
    """The 7-branch synthetic tree, recovered: topology, junction positions, radii, lobe paths."""
    assert len(tree.branches) == 7
    assert [len(b.children) for b in tree.branches].count(2) == 3
    found = np.array([tree.branches[i].points[-1] for i in (0, *tree.branches[0].children)])
    for j in JUNCTIONS:  # skeleton junctions land near the true bifurcations
        assert np.linalg.norm(found - j, axis=1).min() < 3.0
    assert np.median(tree.branches[0].radii) == pytest.approx(4.0, abs=radius_tol)
    right, left = main_bronchi(tree)
    assert tree.branches[right].points[-1, 0] < 0 < tree.branches[left].points[-1, 0]
    ends = {k: p.points[-1] for k, p in tree.lobe_paths.items()}
    assert ends["ur"] == pytest.approx([-22, 0, 22], abs=3.5)
    assert ends["br"] == pytest.approx([-13, 0, 0], abs=3.5)
    assert ends["ul"] == pytest.approx([30, 0, 22], abs=3.5)
    assert ends["bl"] == pytest.approx([22, 0, -1], abs=3.5)


@pytest.mark.parametrize("ext", [".nii.gz", ".nii", ".mhd", ".nrrd"])
def test_volume_sources(tmp_path, mask_and_origin, ext):
    mask, origin = mask_and_origin
    tree = load_anatomy(write_volume(tmp_path / f"seg{ext}", mask, origin, VOXEL))
    check_synthetic_tree(tree, radius_tol=0.5)
    np.testing.assert_allclose(tree.spacing_mm, VOXEL, rtol=1e-6)  # the file's own grid
    np.testing.assert_allclose(tree.origin_mm, origin, atol=1e-4)
    assert tree.name == f"seg{ext}"
    report = mesh_report(tree.surface)
    assert report["boundary_edges"] == 0 and report["non_manifold_edges"] == 0 and report["pieces"] == 1


def test_volume_keeps_largest_component(tmp_path, mask_and_origin):
    mask, origin = mask_and_origin
    noisy = mask.copy()
    noisy[2:4, 2:4, 2:4] = 1  # a speck of segmentation noise away from the airway
    tree = load_anatomy(write_volume(tmp_path / "noisy.mhd", noisy, origin, VOXEL))
    assert len(tree.branches) == 7


@pytest.mark.parametrize("ext", [".stl", ".obj", ".vtp"])
def test_mesh_sources_skeletonised(tmp_path, mesh_surface, ext):
    tree = load_anatomy(write_mesh(tmp_path / f"airway{ext}", mesh_surface), voxel_mm=0.5)
    check_synthetic_tree(tree, radius_tol=0.5)
    np.testing.assert_allclose(tree.spacing_mm, 0.5)
    all_pts = np.concatenate([b.points for b in tree.branches])
    assert np.all(tree.to_voxels(all_pts) > 5)  # origin below the airway by a margin
    assert mesh_report(tree.surface)["boundary_edges"] == 0
    assert lumen_surface(tree).GetNumberOfPolys() == pytest.approx(tree.surface.GetNumberOfPolys(), rel=0.01)


def test_mesh_with_given_centreline(tmp_path, mesh_surface):
    points, radii, edges = tree_graph(synthetic_tree())
    centreline = write_graph(tmp_path / "cl.vtp", points, edges, {"radius": radii})
    tree = load_anatomy(write_mesh(tmp_path / "airway.stl", mesh_surface), centreline=centreline)
    assert len(tree.branches) == 7
    assert tree.branches[0].points[0] == pytest.approx([0.0, 0.0, 60.0])  # exactly the given centreline
    assert tree.surface.GetNumberOfPolys() > 1000


def test_volume_with_given_centreline_keeps_volume_grid(tmp_path, mask_and_origin):
    mask, origin = mask_and_origin
    points, radii, edges = tree_graph(synthetic_tree())
    centreline = write_graph(tmp_path / "cl.vtu", points, edges, {"radius": radii})
    tree = load_anatomy(write_volume(tmp_path / "seg.nrrd", mask, origin, VOXEL), centreline=centreline)
    assert tree.branches[0].points[0] == pytest.approx([0.0, 0.0, 60.0])
    np.testing.assert_allclose(tree.origin_mm, origin, atol=1e-4)
    np.testing.assert_allclose(tree.spacing_mm, VOXEL, rtol=1e-6)
