"""Losses and metrics: hand-computed cases, DE's blindness to roll, finite gradients, accumulation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from bronchocli import geometry as g
from bronchocli import metrics as m


def pose(x=0.0, y=0.0, z=0.0, a=0.0, b=0.0, c=0.0, dtype=torch.float64) -> torch.Tensor:
    return torch.tensor([x, y, z, a, b, c], dtype=dtype)


def test_position_errors_hand_computed():
    p, t = pose(3, 4, 0), pose(0, 0, 0)
    assert m.pos_l2(p, t).item() == pytest.approx(5.0)
    assert m.pos_mse(p, t).item() == pytest.approx(25.0 / 3)


def test_rotation_l2_uses_wrapped_differences():
    # 179° vs -179° differ by 2°, not 358°
    p, t = pose(a=179.0, c=-90.0), pose(a=-179.0, c=90.0)
    assert m.rot_l2(p, t).item() == pytest.approx(math.hypot(2.0, 180.0))
    assert m.rot_mse(p, t).item() == pytest.approx((4.0 + 180.0**2) / 3)


def test_ce_hand_computed_and_zero_for_a_full_turn():
    p, t = pose(a=90.0, b=0.0, c=360.0), pose()
    assert m.cosine_error(p, t).item() == pytest.approx((1 - math.cos(math.pi / 2)) / 3, abs=1e-12)
    assert m.cosine_error(pose(a=360.0, b=-720.0, c=360.0), pose()).item() == pytest.approx(0.0, abs=1e-12)
    # degrees are converted: a 1° error is tiny, not 1 - cos(1 rad)
    assert m.cosine_error(pose(a=1.0), pose()).item() == pytest.approx((1 - math.cos(math.radians(1))) / 3)


def test_de_is_blind_to_roll_about_the_optical_axis_and_ce_is_not():
    R = Rotation.from_euler("XYZ", [10, 20, 30], degrees=True).as_matrix()
    rolled = g.roll_about_forward(R, 40.0)
    e, e_rolled = torch.tensor(g.matrix_to_euler(R)), torch.tensor(g.matrix_to_euler(rolled))
    p, t = torch.cat([torch.zeros(3, dtype=torch.float64), e_rolled]), torch.cat([torch.zeros(3, dtype=torch.float64), e])
    assert m.direction_error(p, t).item() == pytest.approx(0.0, abs=1e-7)
    assert m.cosine_error(p, t).item() > 0.01
    assert m.geodesic(p, t).item() == pytest.approx(40.0, abs=1e-9)


def test_de_hand_computed():
    # yaw (about z) by 30° turns the optical axis by 30°
    assert m.direction_error(pose(c=30.0), pose()).item() == pytest.approx(math.radians(30), abs=1e-12)
    assert m.direction_error(pose(c=180.0), pose()).item() == pytest.approx(math.pi, abs=1e-12)


def test_de_never_nan_even_when_rounding_pushes_the_dot_above_one():
    e = torch.tensor(np.random.default_rng(0).uniform(-180, 180, (10000, 3)))
    p = torch.cat([torch.zeros(10000, 3, dtype=torch.float64), e], 1)
    assert not torch.isnan(m.direction_error(p, p)).any()
    assert not torch.isnan(m.direction_error(p.float(), p.float())).any()
    assert not torch.isnan(m.geodesic(p.float(), p.float())).any()


@pytest.mark.parametrize("name", ["pos_l2", "rot_l2", "de", "ce", "geodesic"])
def test_gradients_are_finite_at_zero_error(name):
    t = pose(1, 2, 3, 10, 20, 30, dtype=torch.float32)
    p = t.clone().requires_grad_(True)
    m.metric_functions()[name](p, t).sum().backward()
    assert torch.isfinite(p.grad).all()


@pytest.mark.parametrize("rot_loss", ["mse", "de", "ce"])
def test_pose_loss_gradient_finite_and_descends(rot_loss):
    t = pose(1, 2, 3, 10, 20, 30, dtype=torch.float32)[None]
    p = (t + torch.tensor([[0.5, -0.5, 0.2, 8.0, -6.0, 5.0]])).requires_grad_(True)
    loss = m.pose_loss(p, t, rot_loss)
    loss.backward()
    assert torch.isfinite(p.grad).all()
    with torch.no_grad():
        assert m.pose_loss(p - 0.01 * p.grad, t, rot_loss) < loss
    zero = t.clone().requires_grad_(True)
    m.pose_loss(zero, t, rot_loss).backward()
    assert torch.isfinite(zero.grad).all()


def test_bounded_rotation_losses_in_units_of_one_label_std():
    """train.rot_scale label_std: DE and CE divided by their value at one label std of error in every angle
    (hand-computed CE, SciPy's rotation for DE's forward axis), as MSE's squared errors are; none: unchanged."""
    scale = torch.tensor([2.0, 3.0, 4.0, 5.0, 7.0, 9.0], dtype=torch.float64)
    gt = pose(1, 2, 3, 10, 20, 30)[None]
    pred = gt + torch.tensor([[0.4, -0.6, 0.8, 3.0, -4.0, 6.0]], dtype=torch.float64)
    pos = float((((pred - gt)[0, :3] / scale[:3]) ** 2).mean())
    ce_unit = float(np.mean(1 - np.cos(np.deg2rad([5.0, 7.0, 9.0]))))
    forward = Rotation.from_euler("XYZ", [5.0, 7.0, 9.0], degrees=True).apply([1.0, 0.0, 0.0])
    de_unit = math.acos(forward[0])  # the angle between (1, 0, 0) and its image
    for name, unit in (("ce", ce_unit), ("de", de_unit)):
        raw = float(m.metric_functions()[name](pred, gt)[0])
        scaled = float(m.pose_loss(pred, gt, name, scale=scale, rot_scale=True))
        assert scaled == pytest.approx(pos + raw / unit, rel=1e-9)
        assert float(m.pose_loss(pred, gt, name, scale=scale)) == pytest.approx(pos + raw, rel=1e-9)
        one_std = torch.zeros(1, 6, dtype=torch.float64)
        one_std[0, 3:] = scale[3:]
        at_one_std = float(m.pose_loss(one_std, torch.zeros_like(one_std), name, scale=scale, rot_scale=True))
        assert at_one_std == pytest.approx(1.0, rel=1e-9)  # no position error: the rotation term alone, 1
    # MSE is already in std units: rot_scale changes nothing
    assert float(m.pose_loss(pred, gt, "mse", scale=scale, rot_scale=True)) == \
        float(m.pose_loss(pred, gt, "mse", scale=scale))


def test_unknown_rotation_loss_lists_the_valid_ones():
    with pytest.raises(ValueError, match="mse, de, ce"):
        m.pose_loss(pose()[None], pose()[None], "huber")


def test_pair_metrics_mean_and_population_std():
    pred = np.array([[3, 4, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]], dtype=float)
    gt = np.zeros((2, 6))
    stats = m.pair_metrics(pred, gt, spacing_mm=[0.5, 0.5, 0.5])
    assert stats["pos_l2"] == m.Stat(2.5, 2.5, 2)  # ddof=0
    assert stats["pos_l2_mm"].mean == pytest.approx(1.25)


@pytest.mark.parametrize("frame", g.POSE_FRAMES)
def test_accumulated_metrics_score_the_chained_endpoint(frame):
    rng = np.random.default_rng(1)
    start = np.array([10, 20, 30, 5, -5, 170], dtype=float)
    gt = np.concatenate([rng.normal(0, 1, (20, 3)), rng.normal(0, 3, (20, 3))], 1)
    pred = gt.copy()
    pred[:, 0] += 0.1  # a constant bias of 0.1 voxel per pair along the first coordinate
    stats = m.accumulated_metrics([(start, pred, gt)], frame)
    if frame == "world":
        assert stats["pos_l2"].mean == pytest.approx(2.0)  # 20 pairs x 0.1
    assert stats["rot_l2"].mean == pytest.approx(0.0, abs=1e-9)
    assert stats["pos_l2"].n == 1
    perfect = m.accumulated_metrics([(start, gt, gt), (start, gt, gt)], frame)
    assert perfect["pos_l2"].mean == pytest.approx(0.0, abs=1e-9) and perfect["pos_l2"].n == 2


def test_rotation_errors_of_rotations_do_not_depend_on_the_written_triple():
    rng = np.random.default_rng(2)
    gt = np.column_stack([rng.normal(size=(50, 3)), rng.uniform(-180, 180, (50, 3))])
    gt[:, 4] = rng.uniform(-80, 80, 50)
    other = gt.copy()  # the same rotations as (a+180, 180-b, c+180)
    other[:, 3:] = g.wrap_deg(np.column_stack([gt[:, 3] + 180, 180 - gt[:, 4], gt[:, 5] + 180]))
    as_triples = m.per_pose_errors(other, gt)
    assert as_triples["rot_l2"].min() > 10 and as_triples["ce"].min() > 0.1  # compared triple by triple
    as_rotations = m.per_pose_errors(other, gt, rotations=True)
    for name in ("rot_l2", "ce", "de", "geodesic"):
        assert np.abs(as_rotations[name]).max() < 1e-5, name
    pred = gt + rng.normal(0, 2, gt.shape)
    a = m.per_pose_errors(pred, gt, rotations=True)
    b = m.per_pose_errors(pred, other, rotations=True)
    for name in a:
        np.testing.assert_allclose(a[name], b[name], atol=1e-9)
