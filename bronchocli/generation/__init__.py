"""Synthetic datasets: anatomy -> trajectories -> rendered frames and poses on disk.

``pipeline.generate_dataset`` renders a dataset (VTK); ``sources`` says which
patients a config makes; ``trajectories`` plans camera paths; ``writer``
writes frames, CSVs and the fingerprint atomically. ``ensure_dataset`` (here)
renders the configured dataset when it is missing and imports nothing of VTK
otherwise, so training, sweeps and reports run on machines without VTK once
the dataset exists.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

from .. import extras
from ..config import Config
from ..data.naming import DATASET_JSON
from ..data.source import open_dataset


def needs_generation(cfg: Config) -> bool:
    return cfg.dataset.format == "bronchopose" and not (cfg.paths.dataset / DATASET_JSON).is_file()


def ensure_dataset(cfg: Config, progress: bool = True, note: Callable[[str], None] | None = None) -> Path:
    """The configured dataset root, rendered first when it is a ``bronchopose`` dataset without dataset.json.

    When the folder does not exist at all, ``note`` (default: stderr) is told first, in one line: a mistyped
    ``dataset.root`` would otherwise silently start a long generation.
    """
    if needs_generation(cfg):
        extras.require("render", f"generating the dataset (dataset.root {cfg.paths.dataset} holds none yet)",
                       ("vtkmodules",))
        from .pipeline import generate_dataset  # lazy: VTK loads only when there is rendering to do

        if not cfg.paths.dataset.exists():
            (note or _stderr)(f"dataset.root {cfg.paths.dataset} does not exist: generating a new dataset there "
                              "from dataset.generate (if you meant an existing dataset, fix dataset.root)")
        generate_dataset(cfg, progress=progress)
    else:
        check_dataset(cfg)
    return cfg.paths.dataset


def check_dataset(cfg: Config) -> None:
    """The one dataset check of every command (``train``, ``sweep run``/``plan``, ``tune``, ``data stats``): the
    configured dataset read as training reads it (``data.open_dataset``: a bad name, pose or file is one line,
    exit 2) before anything is planned or started. A ``bronchopose`` dataset not generated yet passes: the
    generator writes a valid one."""
    if not needs_generation(cfg):
        open_dataset(cfg)


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)
