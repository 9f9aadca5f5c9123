"""Report tests on real models: the profiler hook of the ablation table, and a tiny real sweep -> report (and
the sweep's parent run: its plan, outcome and the report's files as artifacts)."""

from __future__ import annotations

from pathlib import Path

from tinydata import write_tiny_dataset

from bronchocli.config import load_config
from bronchocli.reporting.report import measuring_profiler
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import search_runs
from bronchocli.runs.views import README_RATIO


def test_the_measuring_profiler_returns_the_keys_the_ablation_table_reads_and_records_them(tmp_path, monkeypatch):
    import torch

    from bronchocli.models import profile

    record = tmp_path / "cache" / "ablation-latency-cpu-32.json"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # on a busy 2-core machine, two spinning threads make one forward 15x slower
    try:
        row = measuring_profiler(32, "cpu", record, repeats=1)("baseline")
    finally:
        torch.set_num_threads(threads)
    assert row["params"] > 1e6 and row["latency_ms_b1"] > 0 and row["gmacs_per_pair"] > 0
    assert {"device", "image_size", "window", "precision"} <= row.keys()
    assert row["latency_ms_bN"] is None and row["peak_mem_mb"] is None  # batch 1 only: what the table shows

    def no_timing(*a, **k):
        raise AssertionError("a recorded architecture must not be timed again")

    monkeypatch.setattr(profile, "profile_arch", no_timing)
    again = measuring_profiler(32, "cpu", record)("baseline")  # a later report: read from the record
    assert again["latency_ms_b1"] == row["latency_ms_b1"] and again["recorded"] == str(record)


def test_report_after_a_tiny_real_sweep(cli, tmp_path):
    data = write_tiny_dataset(tmp_path / "data", patients=2, trajectories=4, frames=8, image_size=32)
    cfg = tmp_path / "experiments.yaml"
    # Table 6's two models (2 cells, one sweep): the report reads what training really logs
    # (trajectory_errors.csv, predictions.csv, references, budget) for the config's cells.
    cfg.write_text(f"""name: tiny-report
runs: {{uri: "sqlite:///{tmp_path}/runs/mlflow.db", artifacts: {tmp_path}/runs/artifacts,
           checkpoints: {tmp_path}/runs/checkpoints}}
storage: {{url: "sqlite:///{tmp_path}/runs/sweep.db"}}
dataset: {{root: {data}}}
splits: {{train: 2, val: 1, test: 1, cross_subject_val: 1}}
grid: {{arch: [convlstm], rot_loss: [ce], population: [personalized], seed: [0]}}
stages: [{{name: sota, add: [{{arch: offsetnet, rot_loss: mse}}]}}]
data: {{window: 3, workers: 0, cache_dir: {tmp_path}/runs/cache}}
train: {{steps: 2, val_every: 2, batch_size: 6, threads: 1}}
eval: {{rpe_gap: 3}}
""")
    code, _, stderr = cli("sweep", "-c", str(cfg))
    assert code == 0, stderr
    out = tmp_path / "reports"
    code, stdout, stderr = cli("report", "-c", str(cfg), "--table", "sota", "--figures", "--no-latency", "-q",
                               "--out", str(out))
    assert code == 0, stderr
    names = {p.name for p in out.iterdir() if not p.name.startswith(".")}  # not the figure cache's record (.figure-keys.json)
    check_parent(load_config(cfg), names, stdout)
    assert {"table6-sota-accumulated.md", "table6-sota-pair.tex"} <= names
    for stem in ("fig5-trajectories", "fig-skill-table6-sota-pair", "fig-dataset-frames"):
        assert {f"{stem}.png", f"{stem}.pdf"} <= names
    sota = (out / "table6-sota-pair.md").read_text()
    for model in ("BronchoTrack", "OffsetNet", "Zero motion", "Training mean"):
        row = next(line for line in sota.splitlines() if line.startswith(f"| {model} |"))
        assert "—" not in row and row.count("[") == 4, row  # every metric with its interval
    assert "no trajectory_errors.csv" not in stderr and "lacks" not in stderr
    assert "Budget per run: 2 optimiser steps, 12 pairs seen" in sota
    code, _, stderr = cli("report", "-c", str(cfg), "--table", "tracking", "-q", "--out", str(out))
    assert code == 0, stderr
    tracking = (out / "table9-tracking.md").read_text()
    for model in ("| +ConvRNN | MSE+CE (BronchoTrack) |", "| OffsetNet | MSE+MSE (OffsetNet) |",
                  "| Image-blind | Zero motion |",
                  "|  | Training mean |"):
        row = next((line for line in tracking.splitlines() if line.startswith(model)), tracking)
        assert "—" not in row and row.count("[") == 7, row  # CTF, CTF mm, ATE vox/mm, RPE trans/rot, drift
    assert "relative-motion error over 3 frames" in tracking and not (out / "table9-tracking-pair.md").exists()


def check_parent(cfg, written: set[str], stdout: str) -> None:
    """The sweep's parent run: the plan that ran, the best cell with its headline, and the report's files among
    its artifacts (report/), read back through the MLflow client as the UI reads them."""
    client = client_for(cfg)
    (parent,) = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "sweep"})
    params, metrics, tags = parent.data.params, parent.data.metrics, parent.data.tags
    assert params["stage.sota.arch"] == "convlstm,offsetnet" and params["stage.sota.rot_loss"] == "ce,mse"
    assert params["stage.sota.cells"] == "2" and params["cells"] == "2" and "grid.arch" not in params
    assert (metrics["cells.finished"], metrics["cells.failed"]) == (2, 0)
    best = client.get_run(tags["best.sota.run"])
    assert metrics["best.sota.val_best.pos_l2"] == best.data.metrics["val_best.pos_l2"]
    assert metrics[f"best.sota.{README_RATIO}"] == best.data.metrics[README_RATIO]  # its headline, as logged
    logged = {Path(a.path).name for a in client.list_artifacts(parent.info.run_id, "report")}
    assert written <= logged and "table6-sota-pair.md" in logged and "fig5-trajectories.png" in logged
    table = Path(client.download_artifacts(parent.info.run_id, "report/table6-sota-pair.md")).read_text()
    assert "| BronchoTrack |" in table
    assert f"logged {len(written)} file(s) to the parent run {parent.info.run_id}" in stdout
