"""A tiny dataset + config shared by the training tests (no VTK: tests/tinydata.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli.config import load_config


@pytest.fixture(scope="module")
def tiny_project(tmp_path_factory) -> Path:
    """A folder with a 2-patient, 2-lobe, 3-trajectory dataset of 8 frames at 32 px and its config."""
    root = tmp_path_factory.mktemp("project")
    write_tiny_dataset(root / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    write_config(root)
    return root


@pytest.fixture(scope="module")
def tiny_cfg(tiny_project):
    return load_config(tiny_project / "experiments.yaml")
