"""Centreline graphs from .vtu/.vtp: the real CT-derived tree, lobe paths, and graph-building edge cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from synthetic_airway import synthetic_tree, tree_graph, write_graph

from bronchocli.anatomy import load_anatomy, main_bronchi, save_centreline, up_vector
from bronchocli.anatomy.graph import tree_from_graph

REAL_TREE = Path(__file__).resolve().parents[1] / "fixtures" / "airways" / "TestSubject002MajorAirways.vtu"


@pytest.fixture(scope="module")
def real():
    return load_anatomy(REAL_TREE)


def test_real_tree_structure(real):
    # the real tree: 84 end points (83 leaves + the trachea entrance), 82 bifurcations -> 165 branches
    assert len(real.branches) == 165
    assert sum(not b.children for b in real.branches) == 83
    all_pts = np.concatenate([b.points for b in real.branches])
    assert real.branches[0].points[0, 2] == pytest.approx(all_pts[:, 2].max())  # root at the top
    assert np.median(real.branches[0].radii) > 6.0  # and it is the widest airway
    for i, b in enumerate(real.branches):
        for c in b.children:
            np.testing.assert_allclose(real.branches[c].points[0], b.points[-1])
            assert real.branches[c].generation == b.generation + 1 and c > i
    np.testing.assert_allclose(real.spacing_mm, 0.5)
    assert np.all(real.to_voxels(all_pts - 8.2) > 0)  # margin beyond the widest radius (8.19 mm)


def test_real_tree_right_main_bronchus(real):
    right, left = main_bronchi(real)
    rb, lb = real.branches[right], real.branches[left]
    down = -up_vector(real)
    chord = lambda b: (b.points[-1] - b.points[0]) / np.linalg.norm(b.points[-1] - b.points[0])  # noqa: E731
    assert rb.length < lb.length and chord(rb) @ down > chord(lb) @ down
    assert rb.length == pytest.approx(22.0, abs=1.0) and lb.length == pytest.approx(57.0, abs=1.5)
    assert rb.points[-1, 0] < lb.points[-1, 0]  # this file is LPS-like: the patient's right is -x


def test_real_tree_lobe_paths(real):
    paths = real.lobe_paths
    assert set(paths) == {"ur", "br", "ul", "bl"}
    end = {k: p.points[-1] for k, p in paths.items()}
    carina_x = real.branches[0].points[-1, 0]
    assert end["ur"][0] < carina_x and end["br"][0] < carina_x  # right lung on one side ...
    assert end["ul"][0] > carina_x and end["bl"][0] > carina_x  # ... left on the other
    assert end["ur"][2] > end["br"][2] + 50 and end["ul"][2] > end["bl"][2] + 50  # upper above lower
    for p in paths.values():
        np.testing.assert_allclose(p.points[0], real.branches[0].points[0])
        assert 4 <= p.generation <= 12 and np.all(np.diff(p.arc_length) > 0)
        assert 140 < p.arc_length[-1] < 260
    assert paths["ur"].branches[:2] == paths["br"].branches[:2] != paths["ul"].branches[:2]


def test_real_tree_paths_end_at_the_reference_leaves(real):
    # the lobe paths' leaves as read off a reference figure of this tree (x and z, to ~3 mm)
    reference = {"ur": (-45, -77), "br": (-56, -209), "ul": (50, -92), "bl": (52, -187)}
    for lobe, (x, z) in reference.items():
        end = real.lobe_paths[lobe].points[-1]
        assert abs(end[0] - x) < 3 and abs(end[2] - z) < 3, (lobe, end)


def test_mirrored_tree_keeps_anatomical_sides(real, tmp_path):
    from bronchocli.anatomy.readers import graph_arrays

    points, radii, edges = graph_arrays(REAL_TREE)
    mirrored = load_anatomy(write_graph(tmp_path / "m.vtp", points * [-1, 1, 1], edges, {"radius": radii}))
    for lobe in ("ur", "br", "ul", "bl"):  # the right lung is now at +x, and still called right
        np.testing.assert_allclose(mirrored.lobe_paths[lobe].points[-1] * [-1, 1, 1],
                                   real.lobe_paths[lobe].points[-1], atol=1e-4)


def test_lobe_generation_cut(real):
    cut = load_anatomy(REAL_TREE, lobe_generation=5)
    for lobe, p in cut.lobe_paths.items():
        assert p.generation == min(5, real.lobe_paths[lobe].generation)
        assert p.branches == real.lobe_paths[lobe].branches[: p.generation + 1]


def test_save_and_reload_round_trip(real, tmp_path):
    back = load_anatomy(save_centreline(real, tmp_path / "airway.vtp"))
    assert len(back.branches) == len(real.branches)
    assert sum(b.length for b in back.branches) == pytest.approx(sum(b.length for b in real.branches), rel=1e-6)
    for lobe in real.lobe_paths:
        np.testing.assert_allclose(back.lobe_paths[lobe].points[-1], real.lobe_paths[lobe].points[-1], atol=1e-4)
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.parametrize("ext", [".vtu", ".vtp"])
def test_graph_file_with_shared_nodes(tmp_path, ext):
    tree = synthetic_tree()
    points, radii, edges = tree_graph(tree)
    loaded = load_anatomy(write_graph(tmp_path / f"g{ext}", points, edges, {"radius": radii}), voxel_mm=0.4)
    assert len(loaded.branches) == 7
    assert sorted(round(b.length, 3) for b in loaded.branches) == sorted(round(b.length, 3) for b in tree.branches)
    np.testing.assert_allclose(loaded.spacing_mm, 0.4)
    right, _ = main_bronchi(loaded)
    assert loaded.branches[right].points[-1, 0] == pytest.approx(-8.0)  # the synthetic right main bronchus
    assert loaded.lobe_paths["ur"].points[-1] == pytest.approx([-22.0, 0.0, 22.0])
    assert loaded.lobe_paths["bl"].points[-1] == pytest.approx([22.0, 0.0, -1.0])


def test_diameter_array_is_halved(tmp_path):
    points, radii, edges = tree_graph(synthetic_tree())
    loaded = load_anatomy(write_graph(tmp_path / "d.vtp", points, edges, {"Diameter": 2 * radii}))
    assert np.median(loaded.branches[0].radii) == pytest.approx(4.0)


def test_duplicate_junction_points_cycles_and_zero_radii():
    tree = synthetic_tree()
    # Each branch as its own polyline (junction points repeated), plus a chord closing a small cycle.
    pts = np.concatenate([b.points for b in tree.branches])
    rad = np.concatenate([b.radii for b in tree.branches])
    rad[-1] = 0.0  # a zero radius at a leaf tip is tolerated
    offsets = np.cumsum([0] + [len(b.points) for b in tree.branches])
    edges = [(i, i + 1) for k in range(len(tree.branches)) for i in range(offsets[k], offsets[k + 1] - 1)]
    edges.append((offsets[0] + 2, offsets[0] + 4))  # cycle inside the trachea
    built = tree_from_graph(pts, rad, np.asarray(edges), name="t", source="t")
    assert len(built.branches) == 7 and np.all(built.branches[-1].radii > 0)
    assert built.branches[0].points[0] == pytest.approx([0.0, 0.0, 60.0])


def test_root_is_the_widest_terminal_branch_not_the_highest():
    tree = synthetic_tree()
    pts, rad, edges = tree_graph(tree)
    flipped = pts * np.array([1.0, 1.0, -1.0])  # upside down: the trachea is now at the bottom
    built = tree_from_graph(flipped, rad, edges, name="t", source="t")
    assert built.branches[0].points[0] == pytest.approx([0.0, 0.0, -60.0])
    assert len(built.branches[0].children) == 2
