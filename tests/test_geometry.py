"""Pose geometry against SciPy's Rotation, incl. gimbal-near angles and ±180° crossings."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from bronchocli import geometry as g

angle = st.floats(-720, 720, allow_nan=False)
beta_near_gimbal = st.sampled_from([90.0, -90.0, 90 - 1e-9, -90 + 1e-7, 89.999, 1e-10])


def random_angles(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    e = rng.uniform(-180, 180, (n, 3))
    e[:, 1] = rng.uniform(-90, 90, n)
    e[: n // 10, 1] = rng.choice([90.0, -90.0, 90 - 1e-10, -90 + 1e-6], n // 10)  # gimbal-near
    return e


def random_trajectory(n: int, seed: int) -> np.ndarray:
    """A random walk whose alpha and gamma cross ±180° several times.

    beta stays inside (-90°, 90°), the range matrix_to_euler returns, so the
    Euler angles themselves (not only the rotations) can be compared.
    """
    rng = np.random.default_rng(seed)
    pos = np.cumsum(rng.normal(0, 2, (n, 3)), 0)
    ang = g.wrap_deg(170 + np.cumsum(rng.normal(0, 25, (n, 3)), 0))
    ang[:, 1] = 85 * np.sin(np.radians(ang[:, 1]))
    return np.concatenate([pos, ang], 1)


def test_euler_to_matrix_matches_scipy():
    e = random_angles(2000)
    ref = Rotation.from_euler("XYZ", e, degrees=True).as_matrix()
    np.testing.assert_allclose(g.euler_to_matrix(e), ref, atol=1e-14)


def test_matrix_to_euler_round_trip_reproduces_the_rotation():
    e = random_angles(2000, seed=1)
    R = Rotation.from_euler("XYZ", e, degrees=True).as_matrix()
    back = g.matrix_to_euler(R)
    np.testing.assert_allclose(g.euler_to_matrix(back), R, atol=1e-13)
    assert np.all(np.abs(back[:, 1]) <= 90 + 1e-12)
    away = np.abs(np.abs(e[:, 1]) - 90) > 1e-3  # angles are unique away from gimbal lock
    np.testing.assert_allclose(g.wrap_deg(back[away] - e[away]), 0, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(a=angle, b=beta_near_gimbal, c=angle)
def test_gimbal_near_round_trip(a, b, c):
    R = Rotation.from_euler("XYZ", [a, b, c], degrees=True).as_matrix()
    np.testing.assert_allclose(g.euler_to_matrix(g.matrix_to_euler(R)), R, atol=1e-12)


def test_matrix_to_euler_agrees_with_scipy_away_from_gimbal():
    R = Rotation.random(500, random_state=3)
    ours = g.matrix_to_euler(R.as_matrix())
    ref = R.as_euler("XYZ", degrees=True)
    ok = np.abs(np.abs(ref[:, 1]) - 90) > 1e-3
    np.testing.assert_allclose(g.wrap_deg(ours[ok] - ref[ok]), 0, atol=1e-9)


def test_wrap_interval_is_half_open_at_minus_180():
    w = g.wrap_deg(np.array([180.0, -180.0, 540.0, -540.0, 0.0, 190.0, -190.0, 359.0]))
    np.testing.assert_array_equal(w, [180, 180, 180, 180, 0, -170, 170, -1])
    assert np.all((w > -180) & (w <= 180))
    np.testing.assert_allclose(g.wrap_rad(np.array([np.pi, -np.pi, 3 * np.pi])), np.pi)


def test_camera_relative_pose_is_the_scipy_relative_motion():
    prev, cur = random_trajectory(2, 5)
    d = g.relative_pose(prev, cur, "camera")
    R_prev = Rotation.from_euler("XYZ", prev[3:], degrees=True)
    R_cur = Rotation.from_euler("XYZ", cur[3:], degrees=True)
    np.testing.assert_allclose(d[:3], R_prev.inv().apply(cur[:3] - prev[:3]), atol=1e-12)
    np.testing.assert_allclose(g.euler_to_matrix(d[3:]), (R_prev.inv() * R_cur).as_matrix(), atol=1e-12)


def test_world_relative_pose_wraps_angle_differences():
    prev = np.array([0, 0, 0, 170.0, 10.0, -175.0])
    cur = np.array([1, 2, 3, -170.0, 12.0, 175.0])
    np.testing.assert_allclose(g.relative_pose(prev, cur, "world"), [1, 2, 3, 20, 2, -10])


@pytest.mark.parametrize("frame", g.POSE_FRAMES)
@pytest.mark.parametrize("seed", range(5))
def test_accumulating_relative_poses_reproduces_the_trajectory(frame, seed):
    traj = random_trajectory(300, seed)
    assert (np.abs(np.diff(traj[:, 3])) > 180).sum() >= 2  # really crosses ±180°
    deltas = g.relative_trajectory(traj, frame)
    acc = g.accumulate(traj[0], deltas, frame)
    np.testing.assert_allclose(acc[:, :3], traj[:, :3], atol=1e-9)
    np.testing.assert_allclose(g.euler_to_matrix(acc[:, 3:]), g.euler_to_matrix(traj[:, 3:]), atol=1e-9)
    np.testing.assert_allclose(g.wrap_deg(acc[:, 3:] - traj[:, 3:]), 0, atol=1e-9)


@pytest.mark.parametrize("frame", g.POSE_FRAMES)
def test_compose_inverts_relative_pose(frame):
    traj = random_trajectory(50, 9)
    d = g.relative_pose(traj[:-1], traj[1:], frame)
    back = g.compose(traj[:-1], d, frame)
    np.testing.assert_allclose(back[:, :3], traj[1:, :3], atol=1e-9)
    np.testing.assert_allclose(g.wrap_deg(back[:, 3:] - traj[1:, 3:]), 0, atol=1e-9)


@pytest.mark.parametrize("frame", g.POSE_FRAMES)
def test_numpy_and_torch_agree_batched(frame):
    trajs = np.stack([random_trajectory(20, s) for s in range(4)])  # (4, 20, 6)
    d_np = g.relative_trajectory(trajs, frame)
    d_t = g.relative_trajectory(torch.tensor(trajs), frame)
    assert isinstance(d_t, torch.Tensor) and d_t.shape == (4, 19, 6)
    np.testing.assert_allclose(d_t.numpy(), d_np, atol=1e-10)
    a_np = g.accumulate(trajs[:, 0], d_np, frame)
    a_t = g.accumulate(torch.tensor(trajs[:, 0]), d_t, frame)
    np.testing.assert_allclose(a_t.numpy(), a_np, atol=1e-9)
    e = random_angles(100)
    np.testing.assert_allclose(g.euler_to_matrix(torch.tensor(e)).numpy(), g.euler_to_matrix(e), atol=1e-14)
    np.testing.assert_allclose(g.wrap_deg(torch.tensor(e * 7)).numpy(), g.wrap_deg(e * 7), atol=1e-9)


def test_look_at_rotation_columns_are_forward_left_up():
    R = g.look_at_rotation(np.array([0.0, 0.0, -2.0]), np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(R[:, 0], [0, 0, -1], atol=1e-15)  # forward
    np.testing.assert_allclose(R[:, 2], [0, 1, 0], atol=1e-15)  # up
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(g.forward_vector(g.matrix_to_euler(R)), [0, 0, -1], atol=1e-12)
    with pytest.raises(ValueError, match="parallel"):
        g.look_at_rotation(np.array([1.0, 0, 0]), np.array([2.0, 0, 0]))


def test_roll_about_forward_keeps_the_optical_axis():
    R = Rotation.random(random_state=2).as_matrix()
    rolled = g.roll_about_forward(R, 30.0)
    np.testing.assert_allclose(rolled[:, 0], R[:, 0], atol=1e-14)
    # the up vector turned by +30° about forward: angle measured in the (left, up) plane
    ang = np.degrees(np.arctan2(-rolled[:, 2] @ R[:, 1], rolled[:, 2] @ R[:, 2]))
    np.testing.assert_allclose(ang, 30.0, atol=1e-12)


def test_unknown_pose_frame_is_rejected():
    with pytest.raises(ValueError, match="world, camera"):
        g.relative_pose(np.zeros(6), np.zeros(6), "body")


def test_canonical_euler_is_scipys_xyz_triple_of_the_same_rotation():
    rng = np.random.default_rng(11)
    angles = rng.uniform(-180, 180, (200, 3))  # beta beyond ±90 half of the time: the other form
    canon = g.canonical_euler(angles)
    ref = Rotation.from_euler("XYZ", angles, degrees=True).as_euler("XYZ", degrees=True)
    np.testing.assert_allclose(canon, ref, atol=1e-9)
    assert (np.abs(canon[:, 1]) <= 90).all()
    np.testing.assert_allclose(g.canonical_euler(canon), canon, atol=1e-9)  # idempotent
    np.testing.assert_allclose(g.euler_to_matrix(canon), g.euler_to_matrix(angles), atol=1e-12)
    pose = np.column_stack([rng.normal(size=(200, 3)), angles])
    np.testing.assert_array_equal(g.canonical_pose(pose)[:, :3], pose[:, :3])


def _assert_in_ranges(e) -> None:
    e = np.asarray(e)
    assert np.all(e[..., 0] > -180.0) and np.all(e[..., 0] <= 180.0)
    assert np.all(np.abs(e[..., 1]) <= 90.0)
    assert np.all(e[..., 2] > -180.0) and np.all(e[..., 2] <= 180.0)


BOUNDARY = [(a, b, c) for a in (-180.0, -90.0, -0.0, 0.0, 90.0, 180.0) for b in (-90.0, -89.9999999, 0.0, 90.0)
            for c in (-180.0, -0.0, 0.0, 180.0)]


@pytest.mark.parametrize("lib", ["numpy", "torch"])
def test_euler_angles_stay_inside_the_documented_ranges_at_the_boundaries(lib):
    """Never exactly -180 for alpha/gamma (atan2 of a -0.0 sine), never |beta| > 90 (pi/2 in degrees is
    90 + 1 ulp): the documented ranges hold exactly, and the triples still reproduce their rotations."""
    rng = np.random.default_rng(11)
    near_lock = np.stack([rng.uniform(-180, 180, 500), rng.choice([-1, 1], 500) * (90 - 10 ** rng.uniform(-15, -1, 500)),
                          rng.uniform(-180, 180, 500)], 1)
    angles = np.concatenate([np.array(BOUNDARY), near_lock])
    R = Rotation.from_euler("XYZ", angles, degrees=True).as_matrix()
    turns = np.stack([np.diag(d) for d in ([1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0])])  # 180° turns
    R = np.concatenate([R, turns])
    x = torch.as_tensor(R) if lib == "torch" else R
    e = g.matrix_to_euler(x)
    e = e.numpy() if lib == "torch" else e
    _assert_in_ranges(e)
    np.testing.assert_allclose(g.euler_to_matrix(e), R, atol=1e-12)
    canon = g.canonical_euler(np.array(BOUNDARY))
    _assert_in_ranges(canon)
    np.testing.assert_allclose(g.euler_to_matrix(canon), Rotation.from_euler("XYZ", BOUNDARY, degrees=True).as_matrix(),
                               atol=1e-12)
