"""The claims table and the MLflow store changed by hand (issues 49 and 50): damaged or foreign claims rows, a
heartbeat from the future, a deleted experiment, parent run or cell run, a run id MLflow does not have. Each is
met with one line naming what is wrong and what to do, never a traceback, and never stops the other cells.

Every fault is made on the real stores: the claims SQLite database edited with SQL, MLflow runs and experiments
deleted through MlflowClient."""

from __future__ import annotations

import json
import logging
import re
import sqlite3

import pytest
from rich.console import Console
from sweep_fakes import FAKE, calls, runs_by_cell
from tinydata import write_tiny_dataset

from bronchocli.runs.client import client_for
from bronchocli.runs.parents import KIND_SWEEP, find_parent
from bronchocli.sweep import FINISHED, PENDING, SweepStore, prepare
from bronchocli.sweep.liveness import FutureHeartbeats
from bronchocli.sweep.storage import RUNNING, CellRow

TABLE = "bronchopose_sweep_cells"
REPORT = ("report", "--table", "personalized", "--no-figures", "--no-latency", "-q")  # fast: no model built
FUTURE = "((julianday('now') - 2440587.5) * 86400.0 + 3600)"  # an hour ahead of the database's clock


@pytest.fixture
def project(make_config, tmp_path):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    return make_config(grid_order=True)


def path_of(cfg) -> str:
    return str(cfg.paths.base / "experiments.yaml")


def planned(cfg) -> dict[str, CellRow]:
    """The claims rows of the config's cells (made as `sweep run` makes them), by architecture."""
    store = SweepStore(cfg.paths.storage_url)
    try:
        prepare(cfg, store)
    finally:
        store.close()
    return rows(cfg)


def rows(cfg) -> dict[str, CellRow]:
    store = SweepStore(cfg.paths.storage_url)
    try:
        return {r.label.split("/")[0]: r for r in store.rows(cfg.name)}
    finally:
        store.close()


def sql(cfg, statement: str, *args) -> None:
    db = sqlite3.connect(cfg.paths.base / "sweep.db")
    try:
        with db:
            db.execute(statement, args)
    finally:
        db.close()


def no_traceback(*texts: str) -> None:
    for text in texts:
        assert "Traceback" not in text and "KeyError" not in text and "JSONDecodeError" not in text, text


def one_line(text: str, *needles: str) -> str:
    """The one line of ``text`` holding every needle (exactly one such line)."""
    found = [line for line in text.splitlines() if all(n in line for n in needles)]
    assert len(found) == 1, text
    return found[0]


# -- damaged and foreign claims rows ---------------------------------------------------------------------------


@pytest.mark.parametrize("column, value, problem", [
    ("state", "bogus", "state 'bogus' is not one of pending, running, finished, failed"),
    ("coords", "{bad", "coords '{bad' is not a JSON object"),
    ("heartbeat", "soon", "heartbeat 'soon' is not a number of seconds"),
])
def test_a_damaged_row_is_set_aside_in_one_line_the_other_cells_run_and_repair_brings_it_back(
        cli, project, fake_dir, column, value, problem):
    lstm = planned(project)["lstm"]
    sql(project, f"UPDATE {TABLE} SET {column} = ? WHERE cell_key = ?", value, lstm.cell_key)
    code, out, err = cli("status", "-c", path_of(project))
    no_traceback(out, err)
    assert code == 0
    line = one_line(out, f"claims row t/{lstm.cell_key}", problem)
    assert "`bronchopose status --repair` makes it pending again" in line and "set aside (not run)" in line
    code, out, err = cli("sweep", "run", "-c", path_of(project), *FAKE)
    no_traceback(out, err)
    assert code == 1, out + err  # not every cell finished: the damaged one was set aside
    one_line(out, f"claims row t/{lstm.cell_key}", problem)
    assert "1 damaged (set aside)" in out
    after = rows(project)
    assert after["baseline"].state == FINISHED and runs_by_cell(project) == {after["baseline"].cell_key: 1}
    assert after["lstm"].damage is not None and calls(lstm.cell_key) == 0  # untouched, never run
    code, out, err = cli("status", "-c", path_of(project), "--repair")
    no_traceback(out, err)
    assert code == 0 and f"repaired claims row t/{lstm.cell_key}" in out and "pending again" in out
    repaired = rows(project)["lstm"]
    assert repaired.damage is None and repaired.state == PENDING and repaired.coords == lstm.coords
    code, out, err = cli("sweep", "run", "-c", path_of(project), *FAKE)
    assert code == 0, out + err
    assert runs_by_cell(project) == {r.cell_key: 1 for r in rows(project).values()}


def test_status_all_shows_a_row_whose_coords_name_no_cell_in_one_line(cli, project):
    lstm = planned(project)["lstm"]
    sql(project, f"UPDATE {TABLE} SET coords = ? WHERE cell_key = ?", '{"arch": "transformer"}', lstm.cell_key)
    code, out, err = cli("status", "-c", path_of(project), "--all")
    no_traceback(out, err)
    assert code == 0 and "Baseline MSE+MSE" in out  # the other cells' rows, by their runs' names
    one_line(out, f"claims row t/{lstm.cell_key}", "coords name no cell")


def test_a_heartbeat_from_the_future_is_stale_after_stale_after_s_of_the_readers_clock(cli, project, fake_dir):
    lstm = planned(project)["lstm"]
    sql(project, f"UPDATE {TABLE} SET state = 'running', token = 'skewed', worker = 'fast-clock:77', "
                 f"heartbeat = {FUTURE}, attempts = 1 WHERE cell_key = ?", lstm.cell_key)
    code, out, err = cli("status", "-c", path_of(project))
    no_traceback(out, err)
    assert code == 0
    line = one_line(out, f"claims row t/{lstm.cell_key}", "ahead of the database's clock")
    assert "worker fast-clock:77" in line and "unchanged for sweep.stale_after_s (2 s)" in line
    code, out, err = cli("sweep", "run", "-c", path_of(project), *FAKE)  # before: waited for ever
    no_traceback(out, err)
    assert code == 0, out + err
    after = rows(project)
    assert after["lstm"].state == FINISHED and after["lstm"].worker != "fast-clock:77"
    assert runs_by_cell(project) == {r.cell_key: 1 for r in after.values()}


def test_future_heartbeats_are_overdue_only_when_unchanged_for_stale_after_s():
    now = [100.0]
    watch = FutureHeartbeats(5.0, clock=lambda: now[0])

    def row(hb: float, token: str = "a", state: str = RUNNING) -> CellRow:
        return CellRow("t", "k", 0, "x", {}, state, 1, 1, "w:1", token, hb, None, None, None, None, None, None)

    assert [r.cell_key for r in watch.new([row(2000.0)], now=1000.0)] == ["k"]
    now[0] = 104.0
    assert watch.new([row(2000.0)], now=1004.0) == [] and watch.overdue() == {}
    now[0] = 105.0
    assert watch.overdue() == {"k": 2000.0}
    watch.new([row(2010.0)], now=1005.0)  # its worker renewed it: alive, the wait starts again
    assert watch.overdue() == {}
    now[0] = 111.0
    watch.new([row(2010.0, token="b")], now=1011.0)  # another claim: the wait starts again too
    assert watch.overdue() == {}
    watch.new([row(500.0)], now=1012.0)  # back in the past: the database's clock judges it
    assert watch.overdue() == {} and watch._seen == {}


def test_a_worker_id_of_another_form_is_said_and_its_stale_claim_taken_over(cli, project, fake_dir):
    lstm = planned(project)["lstm"]
    sql(project, f"UPDATE {TABLE} SET state = 'running', token = 'theirs', worker = 'job-7 on the big cluster', "
                 "heartbeat = 1.0, attempts = 1 WHERE cell_key = ?", lstm.cell_key)
    code, out, err = cli("status", "-c", path_of(project))
    no_traceback(out, err)
    assert code == 0
    line = one_line(out, f"claims row t/{lstm.cell_key}", "'job-7 on the big cluster' is not this project's form")
    assert "taken over once it is sweep.stale_after_s (2 s) old" in line
    code, out, err = cli("sweep", "run", "-c", path_of(project), *FAKE)
    no_traceback(out, err)
    assert code == 0, out + err
    assert rows(project)["lstm"].state == FINISHED
    assert runs_by_cell(project) == {r.cell_key: 1 for r in rows(project).values()}


# -- the MLflow store changed by hand ----------------------------------------------------------------------------


def finished_sweep(cli, cfg) -> dict[str, CellRow]:
    code, out, err = cli("sweep", "run", "-c", path_of(cfg), *FAKE)
    assert code == 0, out + err
    return rows(cfg)


def test_a_deleted_experiment_is_one_line_in_sweep_status_and_report(cli, project, fake_dir):
    finished_sweep(cli, project)
    client = client_for(project)
    exp = client.get_experiment_by_name(project.experiment_name)
    client.delete_experiment(exp.experiment_id)
    want = f"MLflow experiment 't' (id {exp.experiment_id}) in sqlite:///"
    for args in (("sweep", "run", *FAKE), ("status",), REPORT, ("sweep", "plan")):
        code, out, err = cli(*args, "-c", path_of(project))
        no_traceback(out, err)
        assert code == 2, (args, out, err)
        line = one_line(err, want)
        assert "was deleted (in the MLflow UI): restore it there" in line and "give the config a new `name`" in line
    assert client.get_experiment(exp.experiment_id).lifecycle_stage == "deleted"  # nothing made in its place
    assert [e.name for e in client.search_experiments()] == ["Default"]


def test_a_deleted_cell_run_makes_status_sweep_and_report_agree_with_mlflow(cli, project, fake_dir, caplog):
    before = finished_sweep(cli, project)
    client = client_for(project)
    client.delete_run(before["lstm"].run_id)
    code, out, err = cli("status", "-c", path_of(project))
    no_traceback(out, err)
    assert code == 0
    line = one_line(out, "1 cell run(s) of sweep 't' in MLflow experiment 't' were deleted")
    assert "restore them there" in line and "`bronchopose sweep run` trains those cells again" in line
    assert re.search(r"\+LSTM MSE\+MSE · s0[^\n]*\s+pending\s", out) and before["lstm"].run_id not in out
    code, out, err = cli(*REPORT, "-c", path_of(project), "--out", str(project.paths.base / "reports"))
    no_traceback(out, err)
    assert code == 0, out + err
    one_line(err + out, "1 cell run(s) of sweep 't'", "were deleted")
    assert "pass --sweep NAME" not in err + out
    with caplog.at_level(logging.WARNING):
        code, out, err = cli("sweep", "run", "-c", path_of(project), *FAKE)
    assert code == 0, out + err
    assert "1 cell run(s) of sweep 't' in MLflow experiment 't' were deleted (in the MLflow UI): their cells are " \
           "not done, and this sweep trains them again" in caplog.text
    after = rows(project)
    assert after["lstm"].state == FINISHED and after["lstm"].run_id != before["lstm"].run_id
    assert after["baseline"].run_id == before["baseline"].run_id
    assert runs_by_cell(project) == {r.cell_key: 1 for r in after.values()}


def test_every_cell_run_deleted_gives_report_the_right_advice(cli, project, fake_dir):
    before = finished_sweep(cli, project)
    client = client_for(project)
    for r in before.values():
        client.delete_run(r.run_id)
    code, out, err = cli(*REPORT, "-c", path_of(project), "--out", str(project.paths.base / "reports"))
    no_traceback(out, err)
    assert code == 2
    line = one_line(err, "2 cell run(s) of sweep 't' in MLflow experiment 't' were deleted")
    assert "pass --sweep NAME" not in line and "restore them there" in line


def test_a_deleted_parent_run_is_said_and_replaced(cli, project, fake_dir, caplog):
    finished_sweep(cli, project)
    client = client_for(project)
    exp = client.get_experiment_by_name(project.experiment_name).experiment_id
    old = find_parent(client, exp, KIND_SWEEP, "t")
    client.delete_run(old)
    code, out, err = cli(*REPORT, "-c", path_of(project), "--out", str(project.paths.base / "reports"))
    no_traceback(out, err)
    assert code == 0, out + err
    said = " ".join((err + out).split())  # the report's console wraps its lines
    assert f"not logged to MLflow: the parent run {old} of sweep 't' was deleted (in the MLflow UI): restore it " \
           "there" in said
    with caplog.at_level(logging.WARNING):
        code, out, err = cli("sweep", "run", "-c", path_of(project), *FAKE)
    no_traceback(out, err)
    assert code == 0, out + err
    assert f"the parent run {old} of sweep 't' was deleted" in caplog.text and "a new parent run is made" in caplog.text
    new = find_parent(client, exp, KIND_SWEEP, "t")
    assert new not in (None, old) and client.get_run(new).info.status == "FINISHED"


def test_a_claims_row_whose_run_mlflow_does_not_have_is_warned_and_repairable(cli, project, fake_dir):
    before = finished_sweep(cli, project)
    sql(project, f"UPDATE {TABLE} SET run_id = 'f00dfeedf00dfeedf00dfeedf00dfeed' WHERE cell_key = ?",
        before["lstm"].cell_key)
    code, out, err = cli("status", "-c", path_of(project))
    no_traceback(out, err)
    assert code == 0
    line = one_line(out, f"claims row t/{before['lstm'].cell_key}", "run f00dfeedf00dfeedf00dfeedf00dfeed does not "
                                                                     "exist in MLflow")
    assert "check runs.uri" in line and "`bronchopose status --repair` makes the cell pending again" in line
    code, out, err = cli("status", "-c", path_of(project), "--repair")
    assert code == 0 and "pending again (its run f00dfeedf00dfeedf00dfeedf00dfeed does not exist in MLflow)" in out
    # pending again; the cell's FINISHED run in MLflow is recorded by the next sweep instead of training it again
    assert rows(project)["lstm"].state == PENDING
    code, out, err = cli("sweep", "run", "-c", path_of(project), *FAKE)
    assert code == 0 and rows(project)["lstm"].run_id == before["lstm"].run_id
    assert calls(before["lstm"].cell_key) == 1


# -- bounds and checks in one place ------------------------------------------------------------------------------


def test_an_empty_only_is_refused(cli, project, fake_dir):
    code, out, err = cli("sweep", "run", "-c", path_of(project), "--only", "", *FAKE)
    no_traceback(out, err)
    assert code == 2 and "--only '': empty" in err and calls("") == 0
    assert not (project.paths.base / "sweep.db").exists()


def test_plan_reports_the_workers_a_run_starts_and_workers_are_bounded(cli, project):
    code, out, err = cli("sweep", "plan", "-c", path_of(project), "--workers", "1000")
    assert code == 0 and "2 pending; workers here: 2" in out, out + err
    for args in (("sweep", "plan"), ("sweep", "run"), ("tune", "--arch", "baseline", "--rot-loss", "mse",
                                                        "--population", "personalized")):
        code, out, err = cli(*args, "-c", path_of(project), "--workers", "10000")
        no_traceback(out, err)
        assert code == 2 and "less than or equal to 1024" in err, (args, err)
    assert not (project.paths.base / "sweep.db").exists()  # refused before anything is made


def test_tune_starts_a_worker_per_trial_at_most(monkeypatch, project):
    from bronchocli.sweep import entry
    from bronchocli.sweep.tuning import launch as trials
    from bronchocli.sweep.launchers import LocalLauncher
    from bronchocli.sweep.tuning.rows import StudyTask

    seen = {}

    class Stop(Exception):
        pass

    def fake_tune(cfg, target, n, *, make_launcher, **kw):
        seen["workers"] = make_launcher(cfg, StudyTask("s", cfg.name), lambda: []).workers
        raise Stop  # before any study is opened or process started

    monkeypatch.setattr(trials, "tune", fake_tune)
    target = project.cell(arch="baseline", rot_loss="mse", population="personalized")
    with pytest.raises(Stop):
        entry.tune(project, target, trials=3, kind=LocalLauncher, options={"workers": 1000, "gpus": "none"},
                   console=Console(quiet=True))
    assert seen["workers"] == 3


def test_sweep_plan_refuses_a_dataset_train_refuses(cli, project):
    meta = project.paths.dataset / "dataset.json"
    data = json.loads(meta.read_text())
    data["lobes"] = ["../.."]
    meta.write_text(json.dumps(data))
    for args in (("sweep", "plan"), ("sweep", "run", *FAKE)):
        code, out, err = cli(*args, "-c", path_of(project))
        no_traceback(out, err)
        assert code == 2, (args, out, err)
        one_line(err, "dataset.json: lobes[0] '../..': a lobe name is a folder name")
    assert not (project.paths.base / "sweep.db").exists()
