"""Optional dependencies: without an extra, the core commands work and the others say which extra to install.

Each case runs the console script in a fresh interpreter whose optional modules are blocked
(``sys.modules[name] = None``: every import of them fails, as on a machine without them).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli import extras
from bronchocli.errors import BronchoError

REPO = Path(__file__).resolve().parents[1]
EVERY_OPTIONAL = ("vtk", "vtkmodules", "skimage", "psycopg", "av")


def run_blocked(blocked, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    code = ("import sys\n"
            f"for name in {tuple(blocked)!r}: sys.modules[name] = None\n"
            "from bronchocli.cli import main\n"
            "sys.argv[0] = 'bronchopose'\n"
            "main()\n")
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=cwd, env=env,
                          timeout=600)


def one_line(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr
    return result.stderr


def test_data_generate_without_vtk_names_the_render_extra(tmp_path):
    err = one_line(run_blocked(("vtk", "vtkmodules"), "data", "generate", "--out", str(tmp_path / "d"),
                               "--patients", "1", "--no-progress", cwd=tmp_path))
    assert "data generate needs the optional dependencies vtk, scikit-image" in err
    assert "pip install 'bronchocli[render]'" in err
    assert not (tmp_path / "d").exists()  # refused before anything was made


def test_train_that_must_generate_its_dataset_names_the_render_extra(tmp_path):
    (tmp_path / "experiments.yaml").write_text("name: t\ndataset: {root: nodata}\n")
    err = one_line(run_blocked(EVERY_OPTIONAL, "train", "-a", "baseline", "-l", "mse", "-P", "personalized",
                               cwd=tmp_path))
    assert "generating the dataset" in err and "nodata" in err and "bronchocli[render]" in err


def test_postgres_storage_without_psycopg_names_the_postgres_extra(tmp_path):
    (tmp_path / "experiments.yaml").write_text("name: t\n")
    err = one_line(run_blocked(("psycopg",), "status", "--storage", "postgresql://bob:hunter2@127.0.0.1:1/db",
                               cwd=tmp_path))
    assert "bronchocli[postgres]" in err and "hunter2" not in err


def test_train_and_report_work_with_no_extra_installed(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    write_config(tmp_path, steps=2)
    trained = run_blocked(EVERY_OPTIONAL, "train", "-a", "baseline", "-l", "mse", "-P", "personalized", "-q",
                          cwd=tmp_path)
    assert trained.returncode == 0 and "FINISHED" in trained.stdout, trained.stdout + trained.stderr
    reported = run_blocked(EVERY_OPTIONAL, "report", "--table", "ablation", "--no-latency", "-q", "--out", "rep",
                           cwd=tmp_path)
    assert reported.returncode == 0, reported.stdout + reported.stderr
    assert (tmp_path / "rep").is_dir() and any((tmp_path / "rep").iterdir())


def test_an_import_error_of_an_optional_module_becomes_the_extra_line():
    err = extras.from_import_error(ModuleNotFoundError("No module named 'av'", name="av"), "reading video")
    assert isinstance(err, BronchoError) and "bronchocli[video]" in str(err) and "reading video" in str(err)
    assert extras.from_import_error(ModuleNotFoundError("x", name="numpy"), "x") is None  # not optional: a bug


def test_require_checks_without_importing(monkeypatch):
    monkeypatch.setitem(sys.modules, "skimage", None)
    with pytest.raises(extras.MissingExtra, match=r"bronchocli\[render\]"):
        extras.require("render", "reading a volume", ("skimage",))
    extras.require("render", "rendering", ("vtkmodules",))  # installed here: no error


def test_reading_a_video_without_pyav_names_the_video_extra(monkeypatch, tmp_path):
    from bronchocli.inference import reader

    monkeypatch.setitem(sys.modules, "av", None)
    with pytest.raises(extras.MissingExtra, match=r"reading a video needs .*bronchocli\[video\]"):
        reader._av()
