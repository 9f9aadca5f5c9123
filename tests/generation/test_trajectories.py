"""Trajectory planning (bronchocli.generation.trajectories) on a hand-made bent tube: walks, speeds, lumen rule, seeding."""

from __future__ import annotations

import numpy as np
import pytest
from generator_refs import (
    polyline_distance,
    reference_ups,
    tube_centreline,
    tube_distance,
)

from bronchocli import geometry
from bronchocli.config import Generate
from bronchocli.errors import DataError
from bronchocli.generation.trajectories import (
    PathSampler,
    plan_lobe,
    plan_trajectory,
    trajectory_rng,
    transported_ups,
)


@pytest.fixture(scope="module")
def path() -> PathSampler:
    points, radii = tube_centreline()
    return PathSampler(points, radii)


def _plan(path, gen, t=0, distance=tube_distance, spacing=0.5):
    return plan_trajectory(path, gen, np.full(3, spacing), distance, trajectory_rng(gen, 0, "ur", t), lobe="ur", index=t)


def test_transported_up_matches_scipy_shortest_arc(path):
    rng = np.random.default_rng(1)
    wiggly = np.cumsum(np.column_stack([rng.normal(0, 0.5, 80), rng.normal(0, 0.5, 80), -np.ones(80)]), 0)
    for pts in (path.points, wiggly):
        ups = transported_ups(pts)
        np.testing.assert_allclose(ups, reference_ups(pts), atol=1e-9)
        t = np.diff(pts, axis=0)
        assert np.abs((ups * t).sum(1)).max() < 1e-9  # perpendicular to the path


def test_look_at_extrapolates_past_the_end(path):
    end = path.points[-1]
    tangent = (end - path.position(np.array(path.length - 2.0)))
    tangent /= np.linalg.norm(tangent)
    np.testing.assert_allclose(path.look_at(np.array(path.length + 5.0)), end + 5.0 * tangent, atol=1e-9)
    np.testing.assert_allclose(path.look_at(np.array(30.0)), [0.0, 0.0, -30.0], atol=1e-9)


def test_random_walk_rules(path):
    gen = Generate(trajectories=3, step_mm=(1.0, 3.0), max_frames=None)
    for t in range(3):
        p = _plan(path, gen, t)
        assert len(p) > 20
        assert np.all(np.abs(p.offset_voxels) <= 2)
        assert np.all(np.abs(p.roll_deg) <= 45) and np.allclose(p.roll_deg % 15, 0)
        steps = np.abs(np.diff(np.column_stack([p.offset_voxels, p.roll_deg / 15]), axis=0))
        assert steps.max() <= 1, "each variation index moves by -1, 0 or +1 per frame"
        inc = np.diff(p.base_index) * gen.base_step_mm
        assert inc.min() >= 1.0 - 0.25 and inc.max() <= 3.0 + 0.25  # rounded to whole base steps
        assert len(np.unique(inc)) > 1, "speeds vary within a trajectory"
        np.testing.assert_allclose(p.arc_mm, p.base_index * gen.base_step_mm)
        # Orientation: forward points at the look-at point, up column is the rolled transported up.
        look = path.look_at(p.arc_mm + gen.look_ahead_mm)
        fwd = (look - p.position_mm) / np.linalg.norm(look - p.position_mm, axis=1, keepdims=True)
        np.testing.assert_allclose(p.rotation[:, :, 0], fwd, atol=1e-12)
        R_check = geometry.euler_to_matrix(geometry.matrix_to_euler(p.rotation))
        np.testing.assert_allclose(R_check, p.rotation, atol=1e-12)


def test_positions_stay_inside_the_lumen_with_margin(path):
    gen = Generate(trajectories=1, max_frames=None, wall_margin_mm=0.4)
    p = _plan(path, gen)
    d, r = tube_distance(p.position_mm)
    assert np.all(d < r - 0.4 + 1e-9)
    np.testing.assert_allclose(p.clearance_mm, r - d, atol=1e-9)
    assert p.rejected == 0 and not p.clamped.any()  # this tube is wide: nothing to reject


def test_narrow_airway_rejects_and_clamps(path):
    """With a 1.2 mm lumen most ±1 mm offsets leave it: proposals are redrawn or clamped, never accepted outside."""
    points, _ = tube_centreline()
    narrow = lambda q: polyline_distance(points, np.full(len(points), 1.2), q)  # noqa: E731
    gen = Generate(trajectories=1, max_frames=None, wall_margin_mm=0.4)
    p = _plan(path, gen, distance=narrow)
    d, r = narrow(p.position_mm)
    assert np.all(d < r - 0.4 + 1e-9)
    assert p.rejected > 0
    tiny = lambda q: polyline_distance(points, np.full(len(points), 0.3), q)  # noqa: E731
    q = _plan(path, gen, distance=tiny)
    assert q.clamped.all() and np.all(q.offset_voxels == 0), "no room at all: clamped onto the centreline"


def test_max_frames_gives_contiguous_segments_at_seeded_starts(path):
    gen = Generate(trajectories=6, max_frames=8, step_mm=(1.0, 2.0))
    plans = plan_lobe(path, gen, np.full(3, 0.5), tube_distance, patient="p00", patient_index=0, lobe="ur")
    assert all(2 <= len(p) <= 8 for p in plans)
    assert len({int(p.base_index[0]) for p in plans}) > 1, "start points differ between trajectories"
    assert all(np.all(np.diff(p.base_index) > 0) for p in plans)
    pairs = plan_lobe(path, Generate(trajectories=20, max_frames=2, step_mm=(1.0, 3.0)), np.full(3, 0.5),
                      tube_distance, patient="p00", patient_index=0, lobe="ur")
    assert all(len(p) == 2 for p in pairs), "a trajectory always has room for its second frame"


def test_plans_are_deterministic_and_independent_per_trajectory(path):
    gen = Generate(trajectories=2, max_frames=None)
    a, b, c = _plan(path, gen, 0), _plan(path, gen, 0), _plan(path, gen, 1)
    np.testing.assert_array_equal(a.rotation, b.rotation)
    np.testing.assert_array_equal(a.offset_voxels, b.offset_voxels)
    assert len(a) != len(c) or not np.array_equal(a.offset_voxels, c.offset_voxels)
    other_seed = _plan(path, Generate(trajectories=2, max_frames=None, seed=5), 0)
    assert len(a) != len(other_seed) or not np.array_equal(a.offset_voxels, other_seed.offset_voxels)


def test_short_path_is_a_clear_error():
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -4.0]])
    short = PathSampler(points, np.full(2, 5.0))
    with pytest.raises(DataError, match="too short"):
        _plan(short, Generate())
