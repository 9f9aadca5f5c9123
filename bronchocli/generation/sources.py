"""Which patients a generator config makes (without rendering anything, or importing VTK)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..config import Config, Generate
from ..data.naming import file_patient_id
from ..data.source import dataset_patients


@dataclass(frozen=True)
class PatientSource:
    patient: str
    index: int  # seeds trajectories (generate.seed + index for procedural anatomies)
    anatomy: str  # 'procedural' or an absolute path
    centreline: str | None
    seed: int


def procedural_patient_id(index: int) -> str:
    """Procedural patient ``index`` (seed = generate.seed + index) -> ``p00``, ``p01``, ..."""
    return f"p{index:02d}"


def patient_sources(gen: Generate, anatomy: Path | None, centreline: Path | None) -> list[PatientSource]:
    """One source per patient: ``patients`` seeded procedural trees, or the one anatomy file."""
    if anatomy is None:
        return [PatientSource(procedural_patient_id(i), i, "procedural", None, gen.seed + i)
                for i in range(gen.patients)]
    return [PatientSource(file_patient_id(anatomy), 0, str(anatomy), str(centreline) if centreline else None,
                          gen.seed)]


def planned_patients(cfg: Config) -> list[str]:
    """The dataset's patients: read from it when it exists, else the ones generation will make."""
    found = dataset_patients(cfg)
    if found is not None:
        return found
    return [s.patient for s in patient_sources(cfg.dataset.generate, cfg.paths.anatomy, cfg.paths.centreline)]
