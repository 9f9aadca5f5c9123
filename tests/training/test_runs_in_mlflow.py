"""Real runs of a sweep, read back through MLflow's client and REST API: what the UI's compare view and runs
table get (params that differ, headline metrics, dataset inputs, source fields, nesting under the sweep)."""

from __future__ import annotations

import json
import platform

import pytest
import torch

from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import TAG_NOTE, TAG_PARENT, TAG_SOURCE_GIT, TAG_SOURCE_NAME, TAG_SOURCE_TYPE
from bronchocli.runs.views import README_RATIO, rounded
from bronchocli.sweep import SweepStore, Worker
from bronchocli.sweep.plan import add_cells
from bronchocli.training.run import run_cell


@pytest.fixture(scope="module")
def swept(tiny_cfg):
    """Two cells that differ in architecture and seed, run for real by a sweep worker (in this process)."""
    cfg = tiny_cfg.with_values({"name": "compare", "train.steps": 2})
    client = client_for(cfg)
    experiment_id(client, cfg)
    store = SweepStore(cfg.paths.storage_url)
    store.ensure_schema()
    cells = [cfg.cell(arch="baseline", rot_loss="mse", population="personalized", seed=0),
             cfg.cell(arch="lstm", rot_loss="mse", population="personalized", seed=1)]
    add_cells(cfg, store, cells)
    assert Worker(cfg, cells, store, run_cell).run() == 0
    runs = {r.cell_key: client.get_run(r.run_id) for r in store.rows(cfg.name)}
    return cfg, client, [runs[c.key] for c in cells]


def test_compare_view_params_differ_in_arch_and_seed(swept):
    cfg, client, (a, b) = swept
    differ = {k for k in set(a.data.params) | set(b.data.params) if a.data.params.get(k) != b.data.params.get(k)}
    assert {"arch", "seed"} <= differ
    assert differ <= {"arch", "seed"}  # everything else the two runs share (the grid is not a run param)
    assert len(a.data.params) <= 32  # not the flattened config (119 keys before)
    assert (a.data.params["threads"], a.data.params["threads.source"]) == ("1", "explicit (train.threads)")


def test_the_rest_api_gives_the_ui_the_same_params(swept, monkeypatch):
    """What the browser's compare view fetches: runs/search over REST (through MLflow's test server app)."""
    cfg, client, runs = swept
    from mlflow.server import app  # lazy: the Flask app reads the store URI from the environment

    app.config["TESTING"] = True
    monkeypatch.setenv("_MLFLOW_SERVER_FILE_STORE", cfg.paths.mlflow_uri)
    monkeypatch.setenv("_MLFLOW_SERVER_ARTIFACT_ROOT", cfg.paths.artifacts.as_uri())
    with app.test_client() as http:
        body = {"experiment_ids": [runs[0].info.experiment_id], "filter": "tags.run_kind = 'cell'"}
        got = http.post("/api/2.0/mlflow/runs/search", json=body)
        assert got.status_code == 200, got.data
        found = {r["info"]["run_id"]: {p["key"]: p["value"] for p in r["data"]["params"]}
                 for r in got.get_json()["runs"]}
    params = [found[r.info.run_id] for r in runs]
    assert (params[0]["arch"], params[0]["seed"]) == ("baseline", "0")
    assert (params[1]["arch"], params[1]["seed"]) == ("lstm", "1")


def test_runs_carry_headline_metrics_inputs_source_and_nest_under_the_sweep(swept):
    cfg, client, runs = swept
    for run in runs:
        m, tags = run.data.metrics, run.data.tags
        # logged to 4 significant digits (issue 48.5: the runs table shows them whole), the errors whole
        assert m[README_RATIO] == rounded(m["pair.pos_l2.mean"] / m["train_mean.pair.pos_l2.mean"])
        better = min(m["zero_motion.pair.pos_l2.mean"], m["train_mean.pair.pos_l2.mean"])
        assert m["skill.pair.pos_l2"] == rounded(1 - m["pair.pos_l2.mean"] / better)
        assert tags["env.torch"] == torch.__version__ and tags["env.cuda"] == (torch.version.cuda or "none")
        assert tags["env.python"] == platform.python_version()
        assert tags[TAG_SOURCE_TYPE] == "LOCAL" and tags[TAG_SOURCE_NAME]
        assert len(tags[TAG_SOURCE_GIT]) == 40  # the config's checkout, else the code's (this one)
        assert "Test: pair position error" in tags[TAG_NOTE]
        assert all(v != "" for v in tags.values()), {k for k, v in tags.items() if v == ""}
        inputs = {i.tags[0].value: i.dataset for i in run.inputs.dataset_inputs}
        assert set(inputs) == {"train", "val", "test"}
        assert {d.digest for d in inputs.values()} == {tags["dataset_fingerprint"][:36]}
        assert json.loads(inputs["test"].profile)["trajectories"] == 4  # 2 patients x 2 lobes x 1 test trajectory
    parents = {r.data.tags[TAG_PARENT] for r in runs}
    assert len(parents) == 1
    parent = client.get_run(parents.pop())
    assert parent.data.tags["run_kind"] == "sweep" and parent.data.tags["sweep"] == "compare"
    # the shared settings; what the plan ran (stage.*) is recorded by the sweep command, not the config's grid
    assert "splits.train" in parent.data.params and "grid.arch" not in parent.data.params
