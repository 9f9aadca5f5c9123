"""Names on disk shared by the dataset writer (generation) and the readers: metadata file, patient ids."""

from __future__ import annotations

import re
from pathlib import Path

DATASET_JSON = "dataset.json"


def file_patient_id(path: str | Path) -> str:
    """A patient id from a file name (an anatomy or a pose CSV): its stem, reduced to [A-Za-z0-9_-]."""
    stem = Path(path).name
    for ext in (".nii.gz", ".vtu", ".vtp", ".nii", ".mhd", ".nrrd", ".stl", ".obj", ".csv"):
        if stem.lower().endswith(ext):
            stem = stem[: -len(ext)]
            break
    return re.sub(r"[^A-Za-z0-9_-]+", "_", stem) or "patient"
