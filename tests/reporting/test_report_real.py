"""Report tests on real models: the profiler hook of the ablation table, and a tiny real sweep -> report."""

from __future__ import annotations

from tinydata import write_tiny_dataset

from bronchocli.reporting.report import measuring_profiler


def test_the_measuring_profiler_returns_the_keys_the_ablation_table_reads():
    row = measuring_profiler(32, "cpu", batch=1, repeats=1)("baseline")
    assert row["params"] > 1e6 and row["latency_ms_b1"] > 0 and row["gmacs_per_pair"] > 0
    assert {"device", "image_size", "window", "precision"} <= row.keys()


def test_report_after_a_tiny_real_sweep(cli, tmp_path):
    data = write_tiny_dataset(tmp_path / "data", patients=2, trajectories=4, frames=8, image_size=32)
    cfg = tmp_path / "experiments.yaml"
    cfg.write_text(f"""name: tiny-report
tracking: {{uri: "sqlite:///{tmp_path}/runs/mlflow.db", artifacts: {tmp_path}/runs/artifacts,
           checkpoints: {tmp_path}/runs/checkpoints}}
storage: {{url: "sqlite:///{tmp_path}/runs/sweep.db"}}
dataset: {{root: {data}}}
splits: {{train: 2, val: 1, test: 1, cross_subject_val: 1}}
grid: {{arch: [convlstm, offsetnet], rot_loss: [ce, mse], population: [personalized, cross-subject], folds: [p00], seed: [0]}}
data: {{window: 3, workers: 0, cache_dir: {tmp_path}/runs/cache}}
train: {{steps: 2, val_every: 2, batch_size: 6, threads: 1}}
""")
    # The two models of Table 6 in both populations (4 cells); the other cells show as "—".
    for only in ("arch=convlstm;rot_loss=ce", "arch=offsetnet;rot_loss=mse"):
        code, _, stderr = cli("sweep", "-c", str(cfg), "--only", only)
        assert code == 0, stderr
    out = tmp_path / "reports"
    code, _, stderr = cli("report", "-c", str(cfg), "--table", "all", "--no-latency", "--out", str(out))
    assert code == 0, stderr
    names = {p.name for p in out.iterdir()}
    for key in ("table2-personalized-accumulated", "table3-personalized-pair", "table4-cross-subject-accumulated",
                "table5-cross-subject-pair", "table6-sota-accumulated", "table6-sota-pair",
                "table7-ablation-accumulated", "table7-ablation-pair"):
        assert {f"{key}.md", f"{key}.tex"} <= names
    for stem in ("fig5-trajectories", "fig-error-position", "fig-error-rotation", "fig-dataset-frames",
                 "fig-dataset-positions"):
        assert {f"{stem}.png", f"{stem}.pdf"} <= names
    sota = (out / "table6-sota-accumulated.md").read_text()
    for model in ("BronchoTrack (ConvLSTM, MSE+CE)", "OffsetNet (MSE+MSE)"):
        row = next(line for line in sota.splitlines() if line.startswith(f"| {model} |"))
        assert "—" not in row, row  # every cell of both models came from the sweep's runs
