"""`bronchopose report` end to end on the fabricated sweep: files written, terminal output, flag errors, no VTK."""

from __future__ import annotations

import builtins
import json
import sys

import pytest
from report_fakes import PROFILES

TABLE_FILES = [f"{key}.{ext}" for key in (
    "table2-personalized-accumulated", "table3-personalized-pair", "table4-cross-subject-accumulated",
    "table5-cross-subject-pair", "table6-sota-accumulated", "table6-sota-pair", "table7-ablation-accumulated",
    "table7-ablation-pair", "table9-tracking") for ext in ("md", "tex")]
FIGURE_STEMS = ["fig5-trajectories", "fig-error-position", "fig-error-rotation"] + [
    f"fig-skill-{k}" for k in dict.fromkeys(f.rsplit(".", 1)[0] for f in TABLE_FILES)
    if k != "table9-tracking"]  # no skill figure: the tracking table has no position/rotation L2 skill
DATASET_STEMS = ["fig-dataset-frames", "fig-dataset-positions"]


def _files(stems):
    return [f"{s}.{ext}" for s in stems for ext in ("png", "pdf")]


def test_one_table_one_evaluation_one_format_and_latency_from_json(cli, golden_store, tmp_path):
    prof = tmp_path / "profile.json"
    prof.write_text(json.dumps(list(PROFILES.values())))
    out = tmp_path / "r"
    code, _, stderr = cli("report", "-c", str(golden_store.config), "-t", "ablation", "--eval", "pair",
                          "--format", "latex", "--latency-from", str(prof), "--out", str(out), "-q")
    assert code == 0, stderr
    # no figures unless --table all; the Methods page its caption points to, in the format written
    assert sorted(p.name for p in out.iterdir()) == ["methods.tex", "table7-ablation-pair.tex"]
    assert r"+LSTM MSE+CE & 14.164 & 3.90 & 0.420 &" in (out / "table7-ablation-pair.tex").read_text()


@pytest.mark.parametrize("args, message", [
    (["--table", "table9"], "--table 'table9': must be one of all, personalized, cross-subject, sota, ablation, "
                            "frames"),
    (["--eval", "final"], "--eval 'final': must be one of accumulated, pair, both"),
    (["--format", "html"], "--format 'html': must be one of md, latex, both"),
    (["--pose-frame", "body"], "--pose-frame 'body'"),
    (["--sweep", "nope"], "no runs of sweep 'nope'"),
])
def test_bad_flags_exit_2_with_one_line(cli, golden_store, args, message):
    code, _, stderr = cli("report", "-c", str(golden_store.config), *args)
    assert code == 2 and message in stderr


def test_a_missing_store_is_not_created(cli, tmp_path):
    path = tmp_path / "experiments.yaml"
    path.write_text(f"name: x\nruns:\n  uri: sqlite:///{tmp_path}/none/mlflow.db\n")
    code, _, stderr = cli("report", "-c", str(path))
    assert code == 2 and "no MLflow store there yet" in stderr
    assert not (tmp_path / "none" / "mlflow.db").exists()


@pytest.fixture
def without_vtk(monkeypatch):
    """Make every VTK import fail, as on a machine without VTK (modules already imported included)."""
    for name in [m for m in sys.modules if m == "vtk" or m.startswith(("vtk.", "vtkmodules"))]:
        monkeypatch.setitem(sys.modules, name, None)
    real_import = builtins.__import__

    def no_vtk(name, *args, **kwargs):
        if name == "vtk" or name.startswith(("vtk.", "vtkmodules")):
            raise ImportError(f"No module named {name!r} (VTK hidden by the test)")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_vtk)


def test_report_all_writes_every_table_and_figure_even_without_vtk(cli, golden_store, tmp_path, without_vtk):
    data = golden_store.cfg.paths.dataset
    vtp = data / "p00" / "airway.vtp"  # a centreline for the positions figure: reading it needs VTK
    vtp.parent.mkdir(exist_ok=True)
    vtp.write_text("<VTKFile/>")
    out = tmp_path / "reports"
    try:
        code, stdout, stderr = cli("report", "-c", str(golden_store.config), "--table", "all", "--no-latency",
                                   "--out", str(out))
    finally:
        vtp.unlink()
    assert code == 0, stderr
    # + the record of what each figure group was drawn from (figures are redrawn only when that changes)
    assert sorted(p.name for p in out.iterdir()) == sorted(TABLE_FILES + _files(FIGURE_STEMS + DATASET_STEMS) +
                                                           [".figure-keys.json", "methods.md", "methods.tex"])
    assert "Table 2. Personalized population, accumulated evaluation" in stdout
    flat = " ".join(stdout.split())  # rich wraps at the terminal width
    assert ("62 of the config's 66 cells have a FINISHED run, 1 superseded duplicate(s), 1 cell(s) with only "
            "unfinished runs (1 run(s)), 3 run(s) of other configs left out") in flat
    err = " ".join(stderr.split())
    assert err.count("duplicate: lstm/ce/personalized/s0/world has 2 FINISHED runs") == 1  # once, not per table
    assert err.count("frames table skipped") == 1
    assert err.count("left out 3 run(s) of sweep 'golden'") == 1
    assert err.count("VTK is not installed here") == 1  # the positions figure is drawn without the centreline
    assert "Latency and GMAC not measured (--no-latency)" in (out / "table7-ablation-pair.md").read_text()
