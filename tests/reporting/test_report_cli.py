"""`bronchopose report` end to end on the fabricated sweep: files written, terminal output, flag errors."""

from __future__ import annotations

import json

import pytest
from report_fakes import EXPERIMENT, PROFILES, SWEEP
from tinydata import write_tiny_dataset

TABLE_FILES = [f"{key}.{ext}" for key in (
    "table2-personalized-accumulated", "table3-personalized-pair", "table4-cross-subject-accumulated",
    "table5-cross-subject-pair", "table6-sota-accumulated", "table6-sota-pair", "table7-ablation-accumulated",
    "table7-ablation-pair") for ext in ("md", "tex")]
FIGURE_FILES = [f"{stem}.{ext}" for stem in ("fig5-trajectories", "fig-error-position", "fig-error-rotation",
                                             "fig-dataset-frames", "fig-dataset-positions") for ext in ("png", "pdf")]


@pytest.fixture
def config(golden_store, tmp_path):
    _, uri, _ = golden_store
    data = write_tiny_dataset(tmp_path / "data", patients=2, trajectories=1, frames=6)
    path = tmp_path / "experiments.yaml"
    path.write_text(f"name: {SWEEP}\ntracking:\n  uri: {uri}\n  experiment: {EXPERIMENT}\n"
                    f"dataset:\n  root: {data}\n")
    return path


def test_report_all_writes_every_table_and_figure(cli, config, tmp_path):
    out = tmp_path / "reports"
    code, stdout, stderr = cli("report", "-c", str(config), "--table", "all", "--no-latency", "--out", str(out))
    assert code == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == sorted(TABLE_FILES + FIGURE_FILES)
    assert "Table 2. Personalized population, accumulated evaluation" in stdout
    flat = " ".join(stdout.split())  # rich wraps at the terminal width
    assert "22 cells with a FINISHED run, 1 superseded duplicate(s), 1 cell(s) with only unfinished runs" in flat
    assert "duplicate: lstm/ce/personalized/s0/world has 2 FINISHED runs" in stderr
    assert stderr.count("duplicate: lstm/ce") == 1  # each warning once, not once per table
    assert "Latency and GMAC not measured (--no-latency)" in (out / "table7-ablation-pair.md").read_text()


def test_one_table_one_evaluation_one_format_and_latency_from_json(cli, config, tmp_path):
    prof = tmp_path / "profile.json"
    prof.write_text(json.dumps(list(PROFILES.values())))
    out = tmp_path / "r"
    code, _, stderr = cli("report", "-c", str(config), "-t", "ablation", "--eval", "pair", "--format", "latex",
                          "--latency-from", str(prof), "--out", str(out), "-q")
    assert code == 0, stderr
    assert [p.name for p in out.iterdir()] == ["table7-ablation-pair.tex"]  # no figures unless --table all
    assert r"+LSTM & 14.164 & 3.90 & 0.420 &" in (out / "table7-ablation-pair.tex").read_text()


@pytest.mark.parametrize("args, message", [
    (["--table", "table9"], "--table 'table9': must be one of all, personalized, cross-subject, sota, ablation"),
    (["--eval", "final"], "--eval 'final': must be one of accumulated, pair, both"),
    (["--format", "html"], "--format 'html': must be one of md, latex, both"),
    (["--pose-frame", "body"], "--pose-frame 'body'"),
    (["--sweep", "nope"], "no runs of sweep 'nope'"),
])
def test_bad_flags_exit_2_with_one_line(cli, config, args, message):
    code, _, stderr = cli("report", "-c", str(config), *args)
    assert code == 2 and message in stderr


def test_a_missing_store_is_not_created(cli, tmp_path):
    path = tmp_path / "experiments.yaml"
    path.write_text(f"name: x\ntracking:\n  uri: sqlite:///{tmp_path}/none/mlflow.db\n")
    code, _, stderr = cli("report", "-c", str(path))
    assert code == 2 and "no MLflow store there yet" in stderr
    assert not (tmp_path / "none" / "mlflow.db").exists()
