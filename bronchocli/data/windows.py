"""Where the training windows of a trajectory start (shared by batches.py and the stats command, no torch).

A trajectory of N frames has N-1 image pairs. A window is ``n_pairs``
consecutive pairs (``n_pairs + 1`` frames); consecutive windows start
``n_pairs - overlap`` pairs apart, so they share ``overlap`` pairs. Windows
start at pair 0 and only whole windows are made: the last ``< stride`` pairs
of a trajectory may fall in no window, and a trajectory with fewer than
``n_pairs`` pairs gives none.
"""

from __future__ import annotations

from ..errors import ConfigError


def check_window(n_pairs: int, overlap: int) -> int:
    """Validate a window size and overlap; return the stride between window starts."""
    if n_pairs < 1:
        raise ConfigError(f"data.window: {n_pairs}: a window needs at least 1 image pair")
    if not 0 <= overlap < n_pairs:
        raise ConfigError(f"data.overlap: {overlap}: must be at least 0 and smaller than the window ({n_pairs} pairs)")
    return n_pairs - overlap


def window_starts(pairs: int, n_pairs: int, overlap: int = 0) -> range:
    """First pair index of every window in a trajectory with ``pairs`` image pairs."""
    stride = check_window(n_pairs, overlap)
    return range(0, max(pairs - n_pairs + 1, 0), stride)
