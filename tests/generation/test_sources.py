"""Which patients a config makes: procedural seeds, one anatomy file, or the dataset already on disk."""

from __future__ import annotations

import subprocess
import sys

from tinydata import write_tiny_dataset

from bronchocli.config import Config, Generate
from bronchocli.generation import needs_generation
from bronchocli.generation.sources import PatientSource, patient_sources, planned_patients, procedural_patient_id


def test_procedural_patients_are_seeded_in_order():
    sources = patient_sources(Generate(patients=3, seed=5), None, None)
    assert [s.patient for s in sources] == ["p00", "p01", "p02"] == [procedural_patient_id(i) for i in range(3)]
    assert [(s.index, s.seed, s.anatomy, s.centreline) for s in sources] == [
        (0, 5, "procedural", None), (1, 6, "procedural", None), (2, 7, "procedural", None)]


def test_an_anatomy_file_is_one_patient_named_after_it(tmp_path):
    anatomy, centreline = tmp_path / "Test Subject.002.vtu", tmp_path / "c.vtp"
    (source,) = patient_sources(Generate(patients=4, seed=2), anatomy, centreline)
    assert source == PatientSource("Test_Subject_002", 0, str(anatomy), str(centreline), 2)
    assert patient_sources(Generate(), anatomy, None)[0].centreline is None


def test_planned_patients_read_an_existing_dataset_else_the_generation_plan(tmp_path):
    root = tmp_path / "ds"
    cfg = Config(name="t", dataset={"root": str(root), "generate": {"patients": 2}})
    assert planned_patients(cfg) == ["p00", "p01"] and needs_generation(cfg)
    file_cfg = cfg.with_values({"dataset.generate.anatomy": str(tmp_path / "lung.nii.gz")})
    assert planned_patients(file_cfg) == ["lung"]
    write_tiny_dataset(root, patients=3, lobes=("ur",), trajectories=1, frames=3, image_size=16)
    assert planned_patients(cfg) == ["p00", "p01", "p02"]  # the dataset's own list wins
    assert not needs_generation(cfg)


def test_ensure_dataset_imports_no_vtk_when_the_dataset_exists(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds", patients=1, lobes=("ur",), trajectories=1, frames=3, image_size=16)
    code = ("import sys; from bronchocli.config import Config; from bronchocli.generation import ensure_dataset; "
            f"print(ensure_dataset(Config(name='t', dataset={{'root': {str(root)!r}}}), progress=False)); "
            "print(sorted(m for m in sys.modules if m.startswith(('vtkmodules', 'bronchocli.render', "
            "'bronchocli.generation.pipeline'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.splitlines() == [str(root), "[]"]
