"""bronchocli.hostfree against NumPy's own functions (accuracy) and IEEE's special cases (signed zeros)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bronchocli import hostfree as hf

RNG = np.random.default_rng(0)
X = RNG.uniform(-20.0, 20.0, 20_000)
Y = RNG.uniform(-5.0, 5.0, 20_000)


def ulps(got, want) -> float:
    return float(np.max(np.abs(got - want) / np.spacing(np.maximum(np.abs(want), 1e-300))))


@pytest.mark.parametrize(("ours", "numpy_fn", "args", "tolerance"), [
    (hf.sin, np.sin, (X,), 1), (hf.cos, np.cos, (X,), 1), (hf.atan, np.arctan, (100 * X,), 1),
    (hf.atan2, np.arctan2, (Y, X), 2), (hf.acos, np.arccos, (X / 20,), 2),
    (hf.exp, np.exp, (30 * X,), 1), (hf.log, np.log, (np.abs(X) * 1e5 + 1e-9,), 1),
])
def test_elementary_functions_are_within_two_ulps_of_numpy(ours, numpy_fn, args, tolerance):
    assert ulps(ours(*args), numpy_fn(*args)) <= tolerance


def test_power_matches_the_operator():
    r = RNG.uniform(0.3, 0.7, 1000)
    assert ulps(hf.power(r, 1 / 2.8), r ** (1 / 2.8)) <= 2


def test_signed_zeros_and_quadrants_follow_ieee():
    for y, x in [(0.0, -0.0), (-0.0, -0.0), (-0.0, 1.0), (0.0, 0.0), (1.0, 0.0), (-1.0, -0.0), (-1.0, -1.0),
                 (1e-300, -1.0), (-3.0, 2.0)]:
        got = hf.atan2(y, x)
        assert got == math.atan2(y, x) or abs(got - math.atan2(y, x)) <= 4e-16
        assert math.copysign(1.0, got) == math.copysign(1.0, math.atan2(y, x))
    assert math.copysign(1.0, hf.sin(-0.0)) == -1.0 and hf.cos(0.0) == 1.0
    assert hf.acos(1.0) == 0.0 and hf.acos(-1.0) == math.pi and np.isnan(hf.acos(1.5))
    assert hf.log(0.0) == -np.inf and np.isnan(hf.log(-1.0)) and hf.exp(0.0) == 1.0
    assert isinstance(hf.sin(1.0), np.float64) and hf.sin(np.zeros((2, 3))).shape == (2, 3)


def test_products_without_blas_equal_the_matrix_product():
    a, b = RNG.normal(size=(7, 3, 3)), RNG.normal(size=(7, 3, 3))
    assert np.allclose(hf.matmul(a, b), a @ b, rtol=0, atol=1e-14)
    assert np.allclose(hf.matvec(a, b[:, 0]), (a @ b[:, 0, :, None])[..., 0], rtol=0, atol=1e-14)
    assert np.allclose(hf.norm(b), np.linalg.norm(b, axis=-1), rtol=1e-15)
    assert hf.dot([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]) == 32.0
