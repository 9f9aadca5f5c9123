"""A tiny training project (dataset + experiments.yaml) for tests that train for real on CPU."""

from __future__ import annotations

import textwrap
from pathlib import Path

CONFIG = """\
    name: tiny
    dataset: {{root: tiny}}
    splits: {{train: 1, val: 1, test: 1, cross_subject_val: 1}}
    grid: {{folds: [p01], seed: [0]}}
    data: {{window: 3, image_size: 32}}
    model: {{dropout: 0.1}}
    train: {{batch_size: 6, steps: {steps}, val_every: {val_every}, bn_recalibrate: 2, threads: 1}}
    runs: {{model_artifact: {model_artifact}}}
"""


def write_config(root: Path, steps: int = 4, val_every: int = 2, model_artifact: str = "none", extra: str = "") -> Path:
    path = root / "experiments.yaml"
    path.write_text(textwrap.dedent(CONFIG.format(steps=steps, val_every=val_every, model_artifact=model_artifact))
                    + extra)
    return path
