"""Patient ids and file names shared by the dataset writer and reader."""

from __future__ import annotations

import json
import re
from pathlib import Path

from ..config import Config

DATASET_JSON = "dataset.json"


def procedural_patient_id(index: int) -> str:
    """Procedural patient ``index`` (seed = generate.seed + index) -> ``p00``, ``p01``, ..."""
    return f"p{index:02d}"


def file_patient_id(path: str | Path) -> str:
    """A patient id from an anatomy file name: its stem, reduced to [A-Za-z0-9_-]."""
    stem = Path(path).name
    for ext in (".nii.gz", ".vtu", ".vtp", ".nii", ".mhd", ".nrrd", ".stl", ".obj"):
        if stem.lower().endswith(ext):
            stem = stem[: -len(ext)]
            break
    return re.sub(r"[^A-Za-z0-9_-]+", "_", stem) or "patient"


def patient_ids_for(cfg: Config) -> list[str]:
    """The patients of the configured dataset: read from it when it exists, else what generation would make.

    A foreign CSV dataset (``dataset.format: csv``) must exist: its patients are read from its CSVs.
    """
    if cfg.dataset.format == "csv":
        from .importer import csv_patients  # noqa: PLC0415 (pandas/PIL only when needed)

        return csv_patients(cfg.resolve(cfg.dataset.root), cfg.dataset.csv)
    meta = cfg.resolve(cfg.dataset.root) / DATASET_JSON
    if meta.is_file():
        return list(json.loads(meta.read_text())["patients"])
    gen = cfg.dataset.generate
    if gen.anatomy == "procedural":
        return [procedural_patient_id(i) for i in range(gen.patients)]
    return [file_patient_id(gen.anatomy)]
