"""A tiny training project (dataset + experiments.yaml) for tests that train for real on CPU."""

from __future__ import annotations

import textwrap
from pathlib import Path

CONFIG = """\
    name: tiny
    dataset: {{root: tiny}}
    splits: {{train: 1, val: 1, test: 1, cross_subject_val: 1}}
    grid: {{folds: [p01]}}
    data: {{window: 3, workers: 0, image_size: 32}}
    model: {{dropout: 0.1}}
    train: {{batch_size: 8, max_epochs: {epochs}, min_epochs: 1, patience: 10, threads: 1}}
    tracking: {{log_checkpoint: {log_checkpoint}}}
"""


def write_config(root: Path, epochs: int = 1, log_checkpoint: bool = False, extra: str = "") -> Path:
    path = root / "experiments.yaml"
    path.write_text(textwrap.dedent(CONFIG.format(epochs=epochs, log_checkpoint=str(log_checkpoint).lower())) + extra)
    return path
