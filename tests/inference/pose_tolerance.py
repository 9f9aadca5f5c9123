"""How close two predictions of the same model must be: relative to each pose component's scale."""

from __future__ import annotations

import numpy as np

# Evaluation scored the fp16-rounded weights the model ships (training.network.round_to_export_), in fp32, in the
# same chunks: what remains is the kernels' summation order (evaluation ran channels-last, the model runs
# contiguous; another process or torch build differs likewise; conftest pins the thread count, the other source).
# These untrained networks amplify it to ~3e-4 of a pose component's scale (0.036 on a component reaching ~130 in
# one CI run), so the tolerance is relative to each component's scale over the trajectory, not to each element:
# an element near zero would otherwise fail.
SCALE_TOL = 2e-3


def assert_close(actual: np.ndarray, desired: np.ndarray) -> None:
    """Within SCALE_TOL of each pose component's largest magnitude."""
    assert actual.shape == desired.shape
    scale = np.abs(desired).max(axis=0)
    worst = (np.abs(actual - desired) / scale).max()
    assert worst <= SCALE_TOL, f"off by {worst:.2e} of a component's scale (allowed {SCALE_TOL:g})"


def close(actual: np.ndarray, desired: np.ndarray) -> bool:
    try:
        assert_close(actual, desired)
    except AssertionError:
        return False
    return True
