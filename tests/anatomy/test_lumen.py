"""Centreline distance / inside-the-lumen queries against a brute-force point-to-polyline reference."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_airway import synthetic_tree

from bronchocli.anatomy import AirwayTree, Branch, Lumen, centreline_distance, load_anatomy, path_at, resample


def polyline_distance(points: np.ndarray, radii: np.ndarray, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact distance to each segment, the closest kept, radius interpolated there (brute force)."""
    a, ab = points[:-1], np.diff(points, axis=0)
    t = np.clip(((query[:, None, :] - a) * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    d = np.linalg.norm(query[:, None, :] - (a + t[..., None] * ab), axis=-1)
    j = np.argmin(d, axis=1)
    rows = np.arange(len(query))
    return d[rows, j], radii[j] * (1 - t[rows, j]) + radii[j + 1] * t[rows, j]


def bent_tube() -> AirwayTree:
    """60 mm straight down, then a quarter circle of radius 40 mm; radius 8 -> 5 mm."""
    straight = np.stack([np.zeros(61), np.zeros(61), np.linspace(0.0, -60.0, 61)], 1)
    theta = np.linspace(0.0, np.pi / 2, 64)[1:]
    arc = np.stack([40 - 40 * np.cos(theta), np.zeros_like(theta), -60 - 40 * np.sin(theta)], 1)
    points = np.concatenate([straight, arc])
    radii = np.linspace(8.0, 5.0, len(points))
    return AirwayTree([Branch(points, radii, None)], origin_mm=np.full(3, -120.0), spacing_mm=np.ones(3))


def test_distance_matches_brute_force_on_bent_tube():
    tree = bent_tube()
    b = tree.branches[0]
    rng = np.random.default_rng(0)
    base = b.points[rng.integers(0, len(b.points), 500)]
    query = base + rng.normal(scale=3.0, size=base.shape)
    dist, radius = centreline_distance(tree, query)
    ref_dist, ref_radius = polyline_distance(b.points, b.radii, query)
    np.testing.assert_allclose(dist, ref_dist, atol=1e-3)  # resampling at 0.1 mm cuts the polyline's corners
    np.testing.assert_allclose(radius, ref_radius, atol=5e-3)


def test_hand_computed_offsets_on_a_straight_trachea():
    tree = synthetic_tree()  # trachea: x = y = 0, z from 60 down to 30, radius 4
    lumen = Lumen(tree)
    q = np.array([[0, 0, 50], [1, 0, 50], [0, 3.9, 45], [0, 4.1, 45]], dtype=float)
    near = lumen.nearest(q)
    np.testing.assert_allclose(near.distance_mm, [0, 1, 3.9, 4.1], atol=1e-9)
    np.testing.assert_allclose(near.radius_mm, 4.0)
    assert list(near.branch) == [0, 0, 0, 0]
    np.testing.assert_array_equal(lumen.inside(q), [True, True, True, False])
    np.testing.assert_array_equal(lumen.inside(q, margin_mm=0.5), [True, True, False, False])
    np.testing.assert_allclose(lumen.clearance(q), [4, 3, 0.1, -0.1], atol=1e-9)


def test_cached_index_is_reused():
    tree = synthetic_tree()
    centreline_distance(tree, np.zeros((1, 3)))
    index = tree.cache["lumen"]
    centreline_distance(tree, np.ones((2, 3)))
    assert tree.cache["lumen"] is index


def test_lobe_path_points_are_on_the_centreline():
    tree = load_anatomy("procedural", seed=3)
    for p in tree.lobe_paths.values():
        s = np.linspace(0, p.arc_length[-1], 50)
        pts, radii = path_at(p, s)
        dist, local = centreline_distance(tree, pts)
        assert dist.max() < 1e-3  # the 0.1 mm resampling cuts the polyline's corners a little
        # at a joint the nearest centreline may be a (thinner) child's start: never a wider radius
        assert np.all(local <= radii * 1.001 + 1e-9)
        assert np.median(np.abs(local / radii - 1)) < 0.01


def test_path_at_and_resample():
    tree = synthetic_tree()
    from bronchocli.anatomy import lobe_path

    p = lobe_path(tree, "ur", 3)
    pts, rad = path_at(p, [-5.0, 0.0, 30.0, 1e6])
    np.testing.assert_allclose(pts[0], [0, 0, 60])
    np.testing.assert_allclose(pts[1], [0, 0, 60])
    np.testing.assert_allclose(pts[2], [0, 0, 30])  # the trachea is 30 mm long
    np.testing.assert_allclose(pts[3], [-22, 0, 22])
    np.testing.assert_allclose(rad[:2], 4.0)
    q, _ = resample(p.points, p.radii, 0.3)
    steps = np.linalg.norm(np.diff(q, axis=0), axis=1)
    assert steps.max() <= 0.3 + 1e-9
    assert steps.sum() == pytest.approx(p.arc_length[-1], abs=0.1)  # corners at the joints are cut
