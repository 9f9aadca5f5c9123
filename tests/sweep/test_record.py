"""MLflow is the record of what finished (issue 32, item 2): a lost or new claims database is rebuilt from MLflow's
FINISHED runs, a claimed cell that already FINISHED is recorded instead of trained, and `train` does not train a
finished cell twice."""

from __future__ import annotations

import pytest
from sweep_fakes import FAKE, calls, fake_runner, runs_by_cell
from tinydata import write_tiny_dataset

from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import cell_tags
from bronchocli.sweep import FINISHED, PENDING, SweepStore, Worker, prepare
from bronchocli.sweep.record import REBUILT


@pytest.fixture
def project(make_config, tmp_path):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    return make_config()


def all_runs(cfg) -> int:
    client = client_for(cfg)
    return len(client.search_runs([experiment_id(client, cfg)], max_results=1000))


def test_a_lost_claims_database_is_rebuilt_from_mlflow_and_no_cell_trains_again(cli, project, fake_dir, tmp_path):
    path = str(tmp_path / "experiments.yaml")
    code, out, err = cli("sweep", "-c", path, "--workers", "1", *FAKE)
    assert code == 0 and "done 2/2" in out, out + err
    keys = set(runs_by_cell(project))
    before = (all_runs(project), {k: calls(k) for k in keys})
    for name in ("sweep.db", "sweep.db-wal", "sweep.db-shm"):
        (tmp_path / name).unlink(missing_ok=True)

    code, out, err = cli("sweep", "plan", "-c", path)  # shown finished, nothing written
    assert code == 0 and "2 cells: 2 finished" in out and "FINISHED in MLflow" in out, out + err
    assert not (tmp_path / "sweep.db").exists()
    code, out, err = cli("status", "-c", path)
    assert code == 0 and "new, or lost" in out and "done 2/2" in out, out + err

    code, out, err = cli("sweep", "-c", path, "--workers", "1", *FAKE)
    assert code == 0 and "done 2/2" in out, out + err
    assert (all_runs(project), {k: calls(k) for k in keys}) == before  # no cell trained, no run added
    rows = SweepStore(project.paths.storage_url).rows(project.name)
    assert {r.state for r in rows} == {FINISHED} and {r.worker for r in rows} == {REBUILT}
    assert {r.run_id for r in rows} == {r.info.run_id for r in client_for(project).search_runs(
        [experiment_id(client_for(project), project)], "tags.run_kind = 'cell'")}
    code, out, err = cli("status", "-c", path)
    assert code == 0 and "2 cell(s) recorded from their FINISHED MLflow runs" in out, out + err


def test_a_claimed_cell_already_finished_in_mlflow_is_recorded_not_trained(project, fake_dir):
    store = SweepStore(project.paths.storage_url)
    plan = prepare(project, store, dataset=False)
    base = plan.cells[0]
    client = client_for(project)
    run_id = client.create_run(experiment_id(client, project), tags=cell_tags(project, base)).info.run_id
    client.set_terminated(run_id, "FINISHED")  # e.g. `bronchopose train` finished it while the row stayed pending
    assert store.rows(project.name, [base.key])[0].state == PENDING
    assert Worker(project, plan.cells, store, fake_runner).run() == 0
    row = store.rows(project.name, [base.key])[0]
    assert (row.state, row.run_id) == (FINISHED, run_id) and calls(base.key) == 0
    assert runs_by_cell(project)[base.key] == 1


def test_train_does_not_train_a_finished_cell_again_unless_asked(cli, project, tmp_path):
    cell = project.cell(arch="baseline", rot_loss="mse", population="personalized")
    client = client_for(project)
    run_id = client.create_run(experiment_id(client, project), tags=cell_tags(project, cell)).info.run_id
    client.set_terminated(run_id, "FINISHED")
    code, out, err = cli("train", "-c", str(tmp_path / "experiments.yaml"), "-a", "baseline", "-l", "mse",
                         "-P", "personalized", "-q")
    assert code == 0 and f"already has a FINISHED run {run_id}" in out and "--again" in out, out + err
    assert all_runs(project) == 1
