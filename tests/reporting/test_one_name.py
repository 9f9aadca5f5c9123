"""Issue 57.2 on a tiny real sweep: one name per model wherever a reviewer meets it -- every table (Markdown and
LaTeX), every figure legend, the MLflow run names and descriptions, the logged models' names -- and a table whose
rows repeat another's is not written (a two-model plan's Tables 2/3 are Table 6's)."""

from __future__ import annotations

import re

import pytest
from tinydata import write_tiny_dataset

from bronchocli import registry
from bronchocli.config import load_config
from bronchocli.reporting import figures, skill_figures
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import search_runs
from bronchocli.training.model_logging import MODEL_NAME_TAG

pytestmark = pytest.mark.heavy

MODELS = {("convlstm", "ce"), ("offsetnet", "mse")}  # the two-model plan of the default profile
REFERENCE_ROWS = {"Zero motion", "Training mean", "Image-blind"}


def _table_names(md: str) -> list[str]:
    """The model names a Markdown table shows: its first column, or, under a group, the paper's name where the label
    gives one ("MSE+CE (BronchoTrack)") else the group and the label."""
    out, group = [], ""
    lines = [ln for ln in md.splitlines() if ln.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    for line in lines[1:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        if header[:2] == ["Network", "Loss"]:
            group = cells[0] or group
            if group in REFERENCE_ROWS:
                continue
            named = re.fullmatch(r".+ \((.+)\)", cells[1])
            out.append(named.group(1) if named else f"{group} {cells[1]}")
        elif cells[0] not in REFERENCE_ROWS:
            out.append(cells[0])
    return out


def test_one_name_per_model_across_tables_figures_runs_and_models(cli, tmp_path, monkeypatch):
    data = write_tiny_dataset(tmp_path / "data", patients=2, trajectories=4, frames=8, image_size=32)
    cfg = tmp_path / "experiments.yaml"
    cfg.write_text(f"""name: names
runs: {{uri: "sqlite:///{tmp_path}/runs/mlflow.db", artifacts: {tmp_path}/runs/artifacts,
           checkpoints: {tmp_path}/runs/checkpoints, model_artifact: fp16}}
storage: {{url: "sqlite:///{tmp_path}/runs/sweep.db"}}
dataset: {{root: {data}}}
splits: {{train: 2, val: 1, test: 1, cross_subject_val: 1}}
grid: {{arch: [convlstm], rot_loss: [ce], population: [personalized], seed: [0]}}
stages: [{{name: sota, add: [{{arch: offsetnet, rot_loss: mse}}]}}]
data: {{window: 3, workers: 0, cache_dir: {tmp_path}/runs/cache}}
train: {{steps: 2, val_every: 2, batch_size: 6, threads: 1}}
""")
    code, _, stderr = cli("sweep", "-c", str(cfg))
    assert code == 0, stderr
    legends: dict[str, list[str]] = {}
    for module in (figures, skill_figures):
        real = module.save_figure

        def capture(fig, path, formats, real=real):
            legends[path.name] = [t.get_text() for ax in fig.axes if ax.get_legend()
                                  for t in ax.get_legend().get_texts()]
            legends[path.name + ":ticks"] = [t.get_text() for ax in fig.axes for t in ax.get_yticklabels()]
            return real(fig, path, formats)
        monkeypatch.setattr(module, "save_figure", capture)
    out = tmp_path / "reports"
    code, stdout, stderr = cli("report", "-c", str(cfg), "--figures", "--no-latency", "--format", "both",
                               "--out", str(out))
    assert code == 0, stderr
    names = {registry.model_name(*m) for m in MODELS}
    assert names == {"BronchoTrack", "OffsetNet"}
    seen: set[str] = set()
    for md in sorted(out.glob("table*.md")):
        shown = _table_names(md.read_text())
        tex = md.with_suffix(".tex").read_text()
        assert all(n in tex for n in shown), md.name  # the LaTeX rows: the same names
        seen |= set(shown)
    # figures: every legend entry that is not a reference or the ground truth names a model by its one name
    for stem, texts in legends.items():
        if stem.endswith(":ticks") and "skill" not in stem:
            continue
        seen |= {t for t in texts if t and t not in REFERENCE_ROWS and t != "ground truth" and not t[0].isdigit()
                 and not t.startswith(("−", "-"))}
    assert {"fig5-trajectories", "fig-error-position"} <= legends.keys()
    assert set(legends["fig-error-position"]) >= names | {"Zero motion", "Training mean"}  # every model, both refs
    # the runs: their names (model, seed, ...) and descriptions, and their logged models
    conf = load_config(cfg)
    client = client_for(conf)
    exp = experiment_id(client, conf)
    runs = search_runs(client, [exp], {"run_kind": "cell"})
    assert len(runs) == len(MODELS)
    for run in runs:
        name = re.fullmatch(r"(.+) · s0 · pers · world", run.info.run_name)
        described = re.match(r".*\*\*(.+?)\*\*, personalized", run.data.tags["mlflow.note.content"], re.S)
        assert name and described, (run.info.run_name, run.data.tags["mlflow.note.content"])
        seen |= {name.group(1), described.group(1)}
        assert name.group(1) == registry.model_name(run.data.tags["arch"], run.data.tags["rot_loss"])
    models = client.search_logged_models(experiment_ids=[exp])
    assert len(models) == len(MODELS)
    seen |= {m.tags[MODEL_NAME_TAG] for m in models}
    assert seen == names, seen  # one name per model, nothing else
    # the two-model plan's personalized tables repeat Table 6 (BronchoTrack and OffsetNet, the same runs): not written
    assert not list(out.glob("table2-*")) and not list(out.glob("table3-*"))
    assert "table2-personalized-accumulated not written: its rows are those of Table 6" in stdout + stderr
