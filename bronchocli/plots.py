"""Matplotlib figures shared by training artifacts and reports (saved with ``io.save_figure``)."""

from __future__ import annotations

import textwrap
from typing import Mapping, Sequence

import matplotlib.pyplot as plt
import numpy as np


def trajectory_figure(
    ground_truth: Sequence[np.ndarray],
    predictions: Mapping[str, Sequence[np.ndarray]],
    titles: Sequence[str] | None = None,
    columns: int = 3,
):
    """3-D trajectories (voxel axes): ground truth vs one or more models, one panel per trajectory.

    ``ground_truth[i]`` and ``predictions[name][i]`` are ``(N, >=3)`` absolute poses; ``ground_truth[i]``
    may be None (a trajectory tracked without ground truth: its first predicted pose is marked instead).
    """
    n = len(ground_truth)
    cols = max(1, min(columns, n))
    rows = max(1, -(-n // cols))
    fig = plt.figure(figsize=(4.2 * cols, 3.8 * rows))
    styles = ["tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange"]
    for i, gt in enumerate(ground_truth):
        ax = fig.add_subplot(rows, cols, i + 1, projection="3d")
        if gt is not None:
            ax.plot(gt[:, 0], gt[:, 1], gt[:, 2], color="black", lw=2, label="ground truth")
        start = gt if gt is not None else next(iter(predictions.values()))[i]
        ax.scatter(*start[0, :3], color="black", s=12)
        for (name, preds), color in zip(predictions.items(), styles):
            p = preds[i]
            ax.plot(p[:, 0], p[:, 1], p[:, 2], color=color, lw=1.4, label=name)
        ax.set_xlabel("x (voxels)")
        ax.set_ylabel("y (voxels)")
        ax.set_zlabel("z (voxels)")
        ax.tick_params(labelsize=7)
        if titles:
            ax.set_title(titles[i], fontsize=9)
        if i == 0:
            ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return fig


def error_curve_figure(curves: Mapping[str, np.ndarray], ylabel: str, title: str = "",
                       references: Mapping[str, np.ndarray] | None = None, caption: str = ""):
    """Error against frame index along trajectories: ``curves[name]`` is ``(n_traj, N)`` (NaN-padded); each of
    ``references`` a dashed grey mean line; ``caption`` wrapped under the axes."""
    fig, ax = plt.subplots(figsize=(6.4, 4.4 if caption else 3.6))
    for name, values in curves.items():
        values = np.atleast_2d(values)
        mean = np.nanmean(values, axis=0)
        std = np.nanstd(values, axis=0)
        x = np.arange(len(mean))
        ax.plot(x, mean, label=name)
        ax.fill_between(x, mean - std, mean + std, alpha=0.2)
    for (name, values), style in zip((references or {}).items(), ("--", ":", "-.")):
        mean = np.nanmean(np.atleast_2d(values), axis=0)
        ax.plot(np.arange(len(mean)), mean, style, color="0.35", label=name)
    ax.set_xlabel("frame")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    if caption:
        fig.text(0.01, 0.01, textwrap.fill(caption, 110), fontsize=6.5, va="bottom", ha="left")
        fig.tight_layout(rect=(0, 0.04 + 0.025 * textwrap.fill(caption, 110).count("\n"), 1, 1))
        return fig
    fig.tight_layout()
    return fig
