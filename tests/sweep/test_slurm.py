"""`bronchopose sweep run --launcher slurm` on a real single-node Slurm cluster (slurm_cluster.py) with two fake GPUs.

Nothing stands in for sbatch, squeue, scancel or scontrol: the daemons run for
the session and every array task is a real worker process that Slurm starts.
Claims live in PostgreSQL; MLflow in a SQLite file under the shared-filesystem
opt-in (one node: every task sees it). Fast fake runners (sweep_fakes.py)
except where a checkpoint resume needs real training.
"""

from __future__ import annotations

import copy
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml
from slurm_cluster import (
    start_cluster,
    start_mlflow_server,
    start_postgres,
    stop_cluster,
    stop_mlflow_server,
    stop_postgres,
)
from sweep_fakes import FAKE, HERE, calls, runs_by_cell
from tinydata import write_tiny_dataset

from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.contract import resume_file
from bronchocli.runs.parents import sweep_parent
from bronchocli.runs.records import TAG_KIND, search_runs
from bronchocli.sweep import FINISHED, PENDING, SweepStore
from bronchocli.sweep.plan import plan_key
from bronchocli.sweep.storage import selections_table
from bronchocli.training import checkpoint

# One cluster for the session: under pytest-xdist (--dist loadgroup) one worker runs every test of this file.
pytestmark = [pytest.mark.slurm, pytest.mark.postgres, pytest.mark.xdist_group("slurm")]
REPO = HERE.parents[1]
LIMIT = 120.0  # bound on every wait: a hang fails the test instead of stalling CI
MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"


@pytest.fixture(scope="session")
def cluster():
    if shutil.which("sbatch") is None or shutil.which("slurmctld") is None:
        if os.environ.get("CI"):
            pytest.fail("Slurm is not installed: .ci/run installs slurm-wlm and munge")
        pytest.skip("Slurm (slurm-wlm, munge) is not installed")
    c = start_cluster(cpus=4, gpus=2)
    yield c
    stop_cluster(c)


@pytest.fixture
def slurm(cluster, monkeypatch, fake_dir):
    """The cluster, with this process's environment set up so that sbatch hands it to every task."""
    monkeypatch.setenv("SLURM_CONF", str(cluster.conf))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(REPO), str(HERE), os.environ.get("PYTHONPATH", "")]))
    yield cluster
    cluster.cancel_all()
    cluster.wait_idle_queue(LIMIT)


def project(make_config, tmp_path, pg_url, *, slurm: dict | None = None, **kw):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    return make_config(storage=pg_url, sweep={"heartbeat_s": 0.5, "stale_after_s": 30.0, "poll_s": 0.2},
                       slurm={"cpus_per_task": 1, "shared_filesystem": True, **(slurm or {})}, grid_order=True, **kw)


def wait_for(predicate, what: str, limit: float = LIMIT, cluster=None, cfg=None):
    """Poll ``predicate`` (bounded); on giving up, the message carries what a CI failure needs: the queue, the
    tail of the task logs and of slurmctld's log."""
    end = time.monotonic() + limit
    while not predicate():
        if time.monotonic() > end:
            extra = f"; queue {cluster.jobs()}" if cluster is not None else ""
            if cfg is not None:
                extra += f"\n--- task logs (tail) ---\n{task_logs(cfg)[-4000:]}"
            if cluster is not None:
                extra += f"\n--- slurmctld.log (tail) ---\n{cluster.log('slurmctld')[-3000:]}"
            raise AssertionError(f"gave up waiting for {what}{extra}")
        if cluster is not None:
            cluster.release_held()
        time.sleep(0.2)


def rows(cfg):
    return SweepStore(cfg.paths.storage_url).rows(cfg.name)


def all_finished(cfg, n: int):
    return lambda: (r := rows(cfg)) and len(r) == n and all(x.state == FINISHED for x in r)


def task_logs(cfg) -> str:
    folder = cfg.paths.base / "runs" / "slurm-logs"
    return "\n".join(f"[{p.name}]\n" + p.read_text(errors="replace") for p in sorted(folder.glob("*.log")))


def test_a_six_cell_sweep_runs_each_cell_once_on_its_own_gpu_and_resubmitting_adds_nothing(
        slurm, cli, make_config, tmp_path, pg_url, fake_dir):
    cfg = project(make_config, tmp_path, pg_url, archs=("baseline", "lstm", "convlstm"), losses=("mse", "ce"),
                  slurm={"tasks": 2})  # two workers for six cells: each task runs several
    path = str(cfg.paths.base / "experiments.yaml")
    for arch in ("baseline", "lstm", "convlstm"):
        (fake_dir / f"block-{arch}").touch()  # every cell waits at the gate: two tasks hold cells at once
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)
    assert code == 0, out + err
    assert re.search(r"submitted Slurm array job \d+: 2 task\(s\)", out), out
    wait_for(lambda: len(list(fake_dir.glob("started-*"))) == 2, "two tasks inside cells", cluster=slurm, cfg=cfg)
    queued = sorted(j["id"] for j in slurm.jobs())
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)  # again, while queued/running
    assert code == 0 and "nothing new to submit: 2 task(s)" in out and "submitted" not in out, out + err
    assert sorted(j["id"] for j in slurm.jobs()) == queued
    started = sorted(fake_dir.glob("started-*"))
    gpus = {(fake_dir / f"gpu-{f.name.split('-')[1]}").read_text() for f in started}
    assert gpus == {"0", "1"}, "the two tasks running at once must see different GPUs"
    (fake_dir / "release").touch()
    wait_for(all_finished(cfg, 6), "every cell finished", cluster=slurm, cfg=cfg)
    slurm.wait_idle_queue(LIMIT)  # idle tasks exit instead of waiting
    finished = rows(cfg)
    assert runs_by_cell(cfg, "FINISHED") == {r.cell_key: 1 for r in finished}
    assert [calls(r.cell_key) for r in finished] == [1] * 6
    for r in finished:  # Slurm set CUDA_VISIBLE_DEVICES per task; the worker id names the task and its GPU
        assert re.fullmatch(r"\S+:\d+ slurm \d+_\d+ gpu[01]", r.worker), r.worker
        assert (fake_dir / f"gpu-{r.cell_key}").read_text() == r.worker[-1]
    code, out, _ = cli("status", "-c", path)
    assert code == 0 and "Slurm task" in out
    assert all(re.search(rf"{r.run_id}.*{re.escape(r.worker.split()[2])}", out) for r in finished), out
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", *FAKE)
    assert code == 0 and "nothing left to run" in out and not slurm.jobs(), out + err


def test_a_requeued_task_gives_its_cell_back_and_no_cell_finishes_twice(slurm, cli, make_config, tmp_path, pg_url,
                                                                        fake_dir):
    cfg = project(make_config, tmp_path, pg_url, archs=("baseline", "lstm"), losses=("mse",))
    path = str(cfg.paths.base / "experiments.yaml")
    (fake_dir / "block-baseline").touch()
    (fake_dir / "block-lstm").touch()
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)
    assert code == 0, out + err
    wait_for(lambda: len(list(fake_dir.glob("started-*"))) == 2, "both tasks inside their cells", cluster=slurm,
             cfg=cfg)
    victim = next(r for r in rows(cfg) if r.state == "running")
    task = victim.worker.split()[2]
    slurm.run("scontrol", "requeue", task)
    wait_for(lambda: next(r for r in rows(cfg) if r.cell_key == victim.cell_key).state == PENDING,
             "the requeued task to give its cell back", cluster=slurm, cfg=cfg)
    wait_for(lambda: calls(victim.cell_key) == 2, "the requeued task to run the cell again", cluster=slurm, cfg=cfg)
    (fake_dir / "release").touch()
    wait_for(all_finished(cfg, 2), "both cells finished", cluster=slurm, cfg=cfg)
    slurm.wait_idle_queue(LIMIT)
    assert runs_by_cell(cfg, "FINISHED") == {r.cell_key: 1 for r in rows(cfg)}
    assert runs_by_cell(cfg, None) == {r.cell_key: 1 for r in rows(cfg)}  # the requeued run was resumed, not doubled
    row = next(r for r in rows(cfg) if r.cell_key == victim.cell_key)
    assert row.attempts == 1  # a release does not count as an attempt
    log = task_logs(cfg)
    assert log.count(f"Slurm task {task}") == 2, log  # the same task ran twice; its log was appended, not truncated


def test_a_two_stage_plan_runs_stage_two_after_its_selection_is_recorded_once(slurm, cli, make_config, tmp_path,
                                                                             pg_url, fake_dir):
    stages = [{"name": "first"}, {"name": "second", "grid": {"seed": [1]}, "select": {"top": 1, "over": ["arch"]}}]
    cfg = project(make_config, tmp_path, pg_url, archs=("baseline", "lstm", "convlstm"), losses=("mse",),
                  stages=stages)
    for arch, val in (("baseline", 3.0), ("lstm", 1.0), ("convlstm", 2.0)):
        (fake_dir / f"val-{arch}-mse").write_text(str(val))
    path = str(cfg.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)
    assert code == 0, out + err
    jobs = re.findall(r"submitted Slurm array job (\d+): (\d+) task\(s\) for stage (\w+)", out)
    assert [(n, s) for _, n, s in jobs] == [("3", "first"), ("1", "second")], out
    assert f"after job(s) {jobs[0][0]}" in out
    wait_for(all_finished(cfg, 4), "both stages finished", cluster=slurm, cfg=cfg)
    store = SweepStore(cfg.paths.storage_url)
    assert store.selection(cfg.name, plan_key(cfg), "second")["selected"] == [{"arch": "lstm"}]
    with store.engine.connect() as conn:
        recorded_at = conn.execute(selections_table.select()).mappings().one()["created_at"]
    second = [r for r in rows(cfg) if r.coords["seed"] == 1]
    assert [r.coords["arch"] for r in second] == ["lstm"]
    assert second[0].claimed_at >= recorded_at
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    assert len(search_runs(client, [exp], {TAG_KIND: "selection"})) == 1  # recorded once
    assert runs_by_cell(cfg, "FINISHED") == {r.cell_key: 1 for r in rows(cfg)}


def test_each_up_front_check_is_one_line_and_exit_2_with_nothing_submitted(slurm, cli, make_config, tmp_path,
                                                                          pg_url, monkeypatch):
    cfg = project(make_config, tmp_path, pg_url, archs=("baseline",), losses=("mse",))
    path = str(cfg.paths.base / "experiments.yaml")
    data = yaml.safe_load(Path(path).read_text())
    cases = {
        "SQLite claims table": ({"storage": {"url": "sqlite:///sweep.db"}, "slurm": {"shared_filesystem": False}},
                                "storage.url"),
        "file/SQLite MLflow store": ({"slurm": {"shared_filesystem": False}}, "runs.uri"),
        "node-local folder": ({"slurm": {"shared_filesystem": False}, "runs": {"uri": pg_url}},
                              "a node-local folder"),
        "bad slurm value": ({"slurm": {"timeout_min": 0}}, "sweep.launchers.slurm.timeout_min"),
        "sbatch option the launcher sets": ({"slurm": {"additional": {"array": "0-9"}}},
                                            "sweep.launchers.slurm.additional"),
        "partition the cluster lacks": ({"slurm": {"partition": "nosuch"}}, "sbatch failed"),
    }
    for name, (over, expected) in cases.items():
        bad = tmp_path / f"bad-{len(name)}.yaml"
        merged = copy.deepcopy(data)
        for key, values in over.items():  # "slurm": the launcher's own section, sweep.launchers.slurm
            (merged["sweep"]["launchers"]["slurm"] if key == "slurm" else merged.setdefault(key, {})).update(values)
        bad.write_text(yaml.safe_dump(merged))
        code, out, err = cli("sweep", "run", "-c", str(bad), "--launcher", "slurm", "--detach")
        lines = [x for x in (out + err).splitlines() if x.strip()]
        assert code == 2 and len(lines) == 1 and expected in lines[0], (name, out + err)
        assert not slurm.jobs(), name
    assert not (tmp_path / "sweep.db").exists()  # refused before anything was created
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach")
    assert code == 2 and "sbatch not found" in out + err and len((out + err).strip().splitlines()) == 1
    assert not slurm.jobs()


def test_scancel_mid_cell_the_cell_is_resumed_from_its_checkpoint_by_another_task(slurm, make_config, tmp_path,
                                                                                  pg_url):
    # real training (no --runner): the resume needs a real checkpoint
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=4, frames=8, image_size=32)
    cfg = make_config(storage=pg_url, archs=("baseline",), losses=("mse",),
                      sweep={"heartbeat_s": 0.5, "stale_after_s": 30.0, "poll_s": 0.2},
                      slurm={"cpus_per_task": 1, "shared_filesystem": True},
                      splits={"train": 2, "val": 1, "test": 1, "cross_subject_val": 1},
                      data={"window": 3, "cache_dir": "cache"},
                      train={"batch_size": 3, "steps": 12, "val_every": 3, "bn_recalibrate": 1, "threads": 1,
                             "max_val_pairs": 6})
    path = str(cfg.paths.base / "experiments.yaml")
    submitter = subprocess.Popen([sys.executable, "-c", MAIN, "sweep", "run", "-c", path, "--launcher", "slurm"],
                                 cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(lambda: any(cfg.paths.checkpoints.glob("*/last.pt")), "the first checkpoint", limit=180, cfg=cfg)
        (row,) = rows(cfg)
        first_task = row.worker.split()[2]
        slurm.run("scancel", first_task)
        out, _ = submitter.communicate(timeout=240)
    finally:
        if submitter.poll() is None:
            submitter.kill()
    assert submitter.returncode == 0, out + task_logs(cfg)
    assert len(re.findall(r"submitted Slurm array job \d+: 1 task", out)) == 2, out  # the top-up after the cancel
    (row,) = rows(cfg)
    assert row.state == FINISHED and row.attempts == 1 and row.worker.split()[2] != first_task
    log = task_logs(cfg)
    stopped = re.search(r"SIGTERM received at step (\d+)/12", log)
    assert stopped and 0 < int(stopped.group(1)) < 12, log
    assert f"resuming run {row.run_id}" in log
    client = client_for(cfg)
    steps = [m.step for m in client.get_metric_history(row.run_id, "val_loss")]
    assert sorted(steps) == [3, 6, 9, 12], steps  # continued from the checkpoint, no step trained twice
    assert runs_by_cell(cfg, "FINISHED") == {row.cell_key: 1} and runs_by_cell(cfg, None) == {row.cell_key: 1}


def test_the_time_limit_warning_releases_the_cell_and_requeues_the_task(slurm, cli, make_config, tmp_path, pg_url,
                                                                      fake_dir):
    cfg = project(make_config, tmp_path, pg_url, archs=("baseline",), losses=("mse",))
    path = str(cfg.paths.base / "experiments.yaml")
    (fake_dir / "block-baseline").touch()
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)
    assert code == 0, out + err
    wait_for(lambda: len(list(fake_dir.glob("started-*"))) == 1, "the task inside its cell", cluster=slurm, cfg=cfg)
    (row,) = rows(cfg)
    task = row.worker.split()[2]
    slurm.run("scancel", "--signal=USR1", "--batch", task)  # what --signal=B:USR1@<s> sends before the time limit
    wait_for(lambda: calls(row.cell_key) == 2, "the requeued task to take the cell again", cluster=slurm, cfg=cfg)
    (fake_dir / "release").touch()
    wait_for(all_finished(cfg, 1), "the cell finished", cluster=slurm, cfg=cfg)
    (row,) = rows(cfg)
    assert row.attempts == 1 and runs_by_cell(cfg, None) == {row.cell_key: 1}
    assert runs_by_cell(cfg, "FINISHED") == {row.cell_key: 1}
    log = task_logs(cfg)
    assert f"time limit near: requeueing Slurm task {task}" in log and log.count(f"Slurm task {task},") == 2, log


def test_cancel_stops_the_sweeps_jobs_and_gives_the_running_cell_back(slurm, cli, make_config, tmp_path, pg_url,
                                                                     fake_dir):
    cfg = project(make_config, tmp_path, pg_url, archs=("baseline", "lstm"), losses=("mse",), slurm={"tasks": 1})
    path = str(cfg.paths.base / "experiments.yaml")
    (fake_dir / "block-baseline").touch()
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)
    assert code == 0, out + err
    wait_for(lambda: len(list(fake_dir.glob("started-*"))) == 1, "the task inside its cell", cluster=slurm, cfg=cfg)
    code, out, err = cli("sweep", "cancel", "-c", path, "--launcher", "slurm")
    assert code == 0 and "cancelled Slurm job(s)" in out, out + err
    slurm.wait_idle_queue(LIMIT)
    assert [r.state for r in rows(cfg)] == [PENDING, PENDING]  # released, not failed; the other never started
    assert runs_by_cell(cfg, "KILLED") == {rows(cfg)[0].cell_key: 1}
    code, out, _ = cli("sweep", "cancel", "-c", path, "--launcher", "slurm")
    assert code == 0 and "no Slurm job of sweep t is queued or running" in out


def test_scancel_of_a_detached_sweeps_stage_one_ends_its_parent_run_and_status_says_so(slurm, cli, make_config,
                                                                                      tmp_path, pg_url, fake_dir):
    """Issue 50: `sweep run --detach`, then `scancel` of stage 1's array: its tasks give their cells back, stage 2's
    task starts (afterany) and leaves them to stage 1; the sweep's parent run stayed RUNNING until the next run. The
    last task to leave ends it KILLED, and `status` says why in one line."""
    from bronchocli.sweep.summary import TAG_STOPPED

    stages = [{"name": "first"}, {"name": "second", "grid": {"seed": [1]}, "select": {"top": 1, "over": ["arch"]}}]
    cfg = project(make_config, tmp_path, pg_url, name="stopped", archs=("baseline", "lstm"), losses=("mse",),
                  stages=stages, slurm={"gpus_per_task": 0})
    for arch in ("baseline", "lstm"):
        (fake_dir / f"block-{arch}").touch()
    path = str(cfg.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)
    assert code == 0, out + err
    first = re.search(r"submitted Slurm array job (\d+): 2 task\(s\) for stage first", out)
    assert first, out
    wait_for(lambda: len(list(fake_dir.glob("started-*"))) == 2, "both stage-1 tasks in their cells", cluster=slurm,
             cfg=cfg)
    client = client_for(cfg)
    parent = sweep_parent(client, cfg, experiment_id(client, cfg))
    assert client.get_run(parent).info.status == "RUNNING"
    slurm.run("scancel", first.group(1))
    wait_for(lambda: not slurm.jobs() and client.get_run(parent).info.status != "RUNNING",
             "every task gone and the parent run ended", cluster=slurm, cfg=cfg)
    run = client.get_run(parent)
    reason = ("no Slurm task of sweep stopped is queued or running and 2 cell(s) are not done (its tasks were "
              "stopped: `scancel`, a node gone); `bronchopose sweep run` resumes it")
    assert run.info.status == "KILLED" and run.data.tags[TAG_STOPPED] == reason, run
    assert run.data.tags["sweep_launcher"] == "slurm" and run.data.tags["sweep_watcher"] == "detached"
    assert {r.state for r in rows(cfg)} == {PENDING}
    code, out, _ = cli("status", "-c", path)
    assert code == 0 and f"stopped sweep stopped: its parent run {parent} ended KILLED: {reason}" in out, out


# -- faults a cluster throws, with the configuration a real cluster uses (issue 30) ------------------------------
# Claims on PostgreSQL, tracking through a real `mlflow server` backed by a PostgreSQL instance of this module's
# own (start_postgres: stopping it touches no other database). Real training where a checkpoint matters.


@pytest.fixture(scope="module")
def services():
    psycopg = pytest.importorskip("psycopg")
    pg = start_postgres()
    art = Path(tempfile.mkdtemp(prefix="bronchopose-mlflow-", dir="/tmp"))
    server = None
    try:
        with psycopg.connect(host="127.0.0.1", port=pg.port, user="postgres", dbname="postgres",
                             autocommit=True) as conn:
            conn.execute("CREATE DATABASE mlflow")
        server = start_mlflow_server(pg.url("mlflow"), art / "artifacts", sys.executable)
        yield pg, server
    finally:
        if server is not None:
            stop_mlflow_server(server)
        stop_postgres(pg)
        shutil.rmtree(art, ignore_errors=True)


def cluster_project(make_config, tmp_path, pg_url, services, name: str, steps: int = 24, archs=("baseline",), **kw):
    """A project (one cell unless ``archs`` says more) that really trains (a checkpoint to resume), tracked by the
    MLflow server."""
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=4, frames=8, image_size=32)
    sweep = {"heartbeat_s": 0.5, "stale_after_s": 10.0, "poll_s": 0.2, **kw.pop("sweep", {})}
    return make_config(storage=pg_url, name=name, archs=archs, losses=("mse",), sweep=sweep,
                       runs={"uri": services[1].url, "checkpoints": "runs/checkpoints", **kw.pop("runs", {})},
                       slurm=kw.pop("slurm", {"cpus_per_task": 1, "shared_filesystem": True}),
                       splits={"train": 2, "val": 1, "test": 1, "cross_subject_val": 1},
                       data={"window": 3, "cache_dir": "cache"},
                       train={"batch_size": 3, "steps": steps, "val_every": 6, "bn_recalibrate": 1, "threads": 1,
                              "max_val_pairs": 6}, **kw)


def watch_sweep(cfg, tmp_path) -> subprocess.Popen:
    path = str(cfg.paths.base / "experiments.yaml")
    return subprocess.Popen([sys.executable, "-c", MAIN, "sweep", "run", "-c", path, "--launcher", "slurm"], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def finish(submitter: subprocess.Popen, cfg, limit: float = 420) -> str:
    try:
        out, _ = submitter.communicate(timeout=limit)
    finally:
        if submitter.poll() is None:
            submitter.kill()
    assert submitter.returncode == 0, out + task_logs(cfg)
    return out


def history(cfg, run_id: str, key: str) -> list[tuple[int, float]]:
    return sorted((m.step, m.value) for m in client_for(cfg).get_metric_history(run_id, key))


def one_finished_run(cfg, attempts: int = 1) -> None:
    (row,) = rows(cfg)
    assert row.state == FINISHED and row.attempts == attempts, row
    assert runs_by_cell(cfg, "FINISHED") == {row.cell_key: 1} and runs_by_cell(cfg, None) == {row.cell_key: 1}
    client = client_for(cfg)
    parent = sweep_parent(client, cfg, experiment_id(client, cfg))
    assert client.get_run(parent).info.status == "FINISHED"  # the sweep's parent run ends with the sweep


@pytest.mark.slow
@pytest.mark.parametrize("on_time_limit", ["requeue", "exit"])
def test_the_time_limit_signal_checkpoints_its_step_and_the_resumed_run_trains_only_the_rest(
        slurm, make_config, tmp_path, pg_url, services, on_time_limit):
    cfg = cluster_project(make_config, tmp_path, pg_url, services, f"usr1-{on_time_limit}",
                          slurm={"cpus_per_task": 1, "shared_filesystem": True, "on_time_limit": on_time_limit})
    submitter = watch_sweep(cfg, tmp_path)
    wait_for(lambda: any(cfg.paths.checkpoints.glob("*/last.pt")), "the first checkpoint", limit=300, cfg=cfg)
    (row,) = rows(cfg)
    task = row.worker.split()[2]
    t0 = time.monotonic()
    slurm.run("scancel", "--signal=USR1", "--batch", task)  # what --signal=B:USR1@<s> sends before the time limit
    # no cluster= here: the hold of the requeued task is released by the watcher itself, not by the test
    wait_for(lambda: (r := rows(cfg)[0]).state == "running" and r.token != row.token, "the cell running again",
             limit=300, cfg=cfg)
    back_s = time.monotonic() - t0
    finish(submitter, cfg)
    log = task_logs(cfg)
    stopped = re.search(r"SIGUSR1 received at step (\d+)/24 \(Slurm's time-limit warning\); checkpoint of step "
                        r"\1 saved to", log)
    assert stopped, log
    step = int(stopped.group(1))
    (row,) = rows(cfg)
    assert history(cfg, row.run_id, "resumed_from_step") == [(step, float(step))]  # resumed at the signal's step
    assert [s for s, _ in history(cfg, row.run_id, "val_loss")] == [6, 12, 18, 24]  # no step trained twice
    one_finished_run(cfg)
    print(f"\nBENCH usr1 ({on_time_limit}): signal at step {step}/24, steps lost 0, cell running again after "
          f"{back_s:.1f} s")


@pytest.mark.slow
def test_a_worker_killed_hard_is_resumed_from_its_checkpoint_after_the_cut_off(slurm, make_config, tmp_path, pg_url,
                                                                             services):
    cfg = cluster_project(make_config, tmp_path, pg_url, services, "kill9")
    submitter = watch_sweep(cfg, tmp_path)
    wait_for(lambda: any(cfg.paths.checkpoints.glob("*/last.pt")), "the first checkpoint", limit=300, cfg=cfg)
    (row,) = rows(cfg)
    os.kill(int(row.worker.split()[0].split(":")[1]), signal.SIGKILL)  # what an OOM kill does
    killed_at = checkpoint.load(resume_file(cfg, row.run_id))["step"]
    out = finish(submitter, cfg)
    log = task_logs(cfg)
    assert f"resuming run {row.run_id}" in log and "nothing to claim" not in log, log
    assert len(re.findall(r"submitted Slurm array job \d+: 1 task", out)) == 2, out  # no task before the cut-off
    assert history(cfg, row.run_id, "resumed_from_step") == [(killed_at, float(killed_at))]
    assert [s for s, _ in history(cfg, row.run_id, "val_loss")] == [6, 12, 18, 24]
    one_finished_run(cfg, attempts=2)  # a takeover counts as an attempt (a run that OOMs again fails for good)
    print(f"\nBENCH kill9: checkpoint of step {killed_at} resumed")


@pytest.mark.slow
def test_the_tracking_database_away_for_30_s_costs_no_attempt_and_leaves_no_run_running(
        slurm, make_config, tmp_path, pg_url, services):
    pg, _ = services
    cfg = cluster_project(make_config, tmp_path, pg_url, services, "outage", steps=36, runs={"busy_timeout_s": 15})
    submitter = watch_sweep(cfg, tmp_path)
    wait_for(lambda: any(cfg.paths.checkpoints.glob("*/last.pt")), "the first checkpoint", limit=300, cfg=cfg)
    pg.stop()
    try:
        time.sleep(30)  # the scenario itself: the MLflow server's database is away this long
    finally:
        pg.start()
    finish(submitter, cfg)
    one_finished_run(cfg)
    (row,) = rows(cfg)
    assert [s for s, _ in history(cfg, row.run_id, "val_loss")] == [6, 12, 18, 24, 30, 36]  # none lost, none twice
    assert runs_by_cell(cfg, "RUNNING") == {}


@pytest.mark.slow
def test_a_resubmitted_stage_one_holds_stage_two_back(slurm, cli, make_config, tmp_path, pg_url, fake_dir, services):
    stages = [{"name": "first"}, {"name": "second", "grid": {"seed": [1]}, "select": {"top": 1, "over": ["arch"]}}]
    cfg = project(make_config, tmp_path, pg_url, name="stages", archs=("baseline", "lstm", "convlstm"),
                  losses=("mse",), stages=stages, runs={"uri": services[1].url},
                  slurm={"gpus_per_task": 0})  # three stage-1 tasks at once on the two-GPU node
    for arch, val in (("baseline", 3.0), ("lstm", 1.0), ("convlstm", 2.0)):
        (fake_dir / f"val-{arch}-mse").write_text(str(val))
        (fake_dir / f"block-{arch}").touch()
    path = str(cfg.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)
    assert code == 0, out + err
    second = re.search(r"submitted Slurm array job (\d+): 1 task\(s\) for stage second", out).group(1)
    wait_for(lambda: len(list(fake_dir.glob("started-*"))) == 3, "three stage-1 tasks in their cells", cluster=slurm,
             cfg=cfg)
    victim = next(r for r in rows(cfg) if r.state == "running")
    slurm.run("scancel", victim.worker.split()[2])
    wait_for(lambda: next(r for r in rows(cfg) if r.cell_key == victim.cell_key).state == PENDING,
             "the cancelled task's cell given back", cluster=slurm, cfg=cfg)
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)
    new = re.search(r"submitted Slurm array job (\d+): 1 task\(s\) for stage first", out)
    assert code == 0 and new, out + err
    assert f"afterany:{new.group(1)}" in slurm.run("scontrol", "show", "job", second).stdout  # stage 2 waits for it
    (fake_dir / "release").touch()
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", *FAKE)  # watches to the end
    assert code == 0, out + err + task_logs(cfg)
    done = rows(cfg)
    first_done = max(r.finished_at for r in done if r.coords["seed"] == 0)
    assert all(r.claimed_at >= first_done for r in done if r.coords["seed"] == 1)  # stage 2 only after stage 1
    stage_two = "".join(p.read_text() for p in (cfg.paths.base / "runs" / "slurm-logs").glob(f"{second}_*.log"))
    assert "nothing to claim" not in stage_two  # no stage-2 task started while stage 1 ran
    assert all(f" {second}_" in r.worker for r in done if r.coords["seed"] == 1)  # stage 2's cell: its own task
    assert runs_by_cell(cfg, "FINISHED") == {r.cell_key: 1 for r in done}
    client = client_for(cfg)
    assert client.get_run(sweep_parent(client, cfg, experiment_id(client, cfg))).info.status == "FINISHED"


@pytest.mark.slow
def test_a_cancel_while_a_submitter_watches_stops_it_and_a_later_run_resumes_each_cell_once(
        slurm, cli, make_config, tmp_path, pg_url, fake_dir, services):
    """Issue 37.2 on the cluster: `sweep cancel` in one shell while `sweep run --launcher slurm` watches in another.
    The watcher submits nothing again (it used to re-submit a new array ~17 s after the scancel) and exits 130;
    the sweep's parent run is KILLED and tagged; the cells are given back; a later explicit run un-cancels and
    finishes each cell exactly once, resuming the KILLED runs."""
    from bronchocli.sweep.summary import TAG_CANCELLED

    cfg = project(make_config, tmp_path, pg_url, name="cancel-watch", archs=("baseline", "lstm"), losses=("mse",),
                  runs={"uri": services[1].url}, slurm={"tasks": 2})
    path = str(cfg.paths.base / "experiments.yaml")
    for arch in ("baseline", "lstm"):
        (fake_dir / f"block-{arch}").touch()
    watcher = subprocess.Popen([sys.executable, "-c", MAIN, "sweep", "run", "-c", path, "--launcher", "slurm", *FAKE],
                               cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               env={**os.environ, "COLUMNS": "200"})
    try:
        wait_for(lambda: len(list(fake_dir.glob("started-*"))) == 2 or watcher.poll() is not None,
                 "both tasks inside their cells", cluster=slurm, cfg=cfg)
        assert watcher.poll() is None, watcher.communicate()[0]
        code, out, err = cli("sweep", "cancel", "-c", path, "--launcher", "slurm")
        assert code == 0 and "cancelled Slurm job(s)" in out, out + err
        watched, _ = watcher.communicate(timeout=LIMIT)
    finally:
        if watcher.poll() is None:
            watcher.kill()
    assert watcher.returncode == 130 and "was cancelled" in watched, watched + task_logs(cfg)
    assert len(re.findall(r"submitted Slurm array job \d+", watched)) == 1, watched  # nothing submitted again
    slurm.wait_idle_queue(LIMIT)
    time.sleep(20)  # longer than the ~17 s after which the watcher used to re-submit: still nothing queued
    assert slurm.jobs() == []
    assert [r.state for r in rows(cfg)] == [PENDING, PENDING]  # the stopped tasks gave their cells back
    client = client_for(cfg)
    parent = client.get_run(sweep_parent(client, cfg, experiment_id(client, cfg)))
    assert parent.info.status == "KILLED" and TAG_CANCELLED in parent.data.tags
    assert runs_by_cell(cfg, "KILLED") == {r.cell_key: 1 for r in rows(cfg)}

    (fake_dir / "release").touch()
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", *FAKE)  # un-cancels, watches to the end
    assert code == 0, out + err + task_logs(cfg)
    done = rows(cfg)
    assert {r.state for r in done} == {FINISHED}
    assert runs_by_cell(cfg, "FINISHED") == {r.cell_key: 1 for r in done} == runs_by_cell(cfg, None)  # resumed
    parent = client.get_run(parent.info.run_id)
    assert parent.info.status == "FINISHED" and TAG_CANCELLED not in parent.data.tags


@pytest.mark.slow
def test_stage_one_cancelled_whole_lets_stage_two_start_but_it_takes_no_stage_one_work(
        slurm, cli, make_config, tmp_path, pg_url, fake_dir, services):
    """Issue 37.3 as reported: `scancel` of the whole stage-1 array meets stage 2's `afterany` at once, so a stage-2
    task starts while stage 1 is unfinished (docs/cluster.md: the guarantee is about work, not start times); it
    exits without claiming any stage-1 cell, and the command run again runs stage 1 before stage 2."""
    stages = [{"name": "first"}, {"name": "second", "grid": {"seed": [1]}, "select": {"top": 1, "over": ["arch"]}}]
    cfg = project(make_config, tmp_path, pg_url, name="stages-cut", archs=("baseline", "lstm"), losses=("mse",),
                  stages=stages, runs={"uri": services[1].url}, slurm={"gpus_per_task": 0})
    for arch, val in (("baseline", 2.0), ("lstm", 1.0)):
        (fake_dir / f"val-{arch}-mse").write_text(str(val))
        (fake_dir / f"block-{arch}").touch()
    path = str(cfg.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", "--detach", *FAKE)
    assert code == 0, out + err
    first = re.search(r"submitted Slurm array job (\d+): 2 task\(s\) for stage first", out)
    second = re.search(r"submitted Slurm array job (\d+): 1 task\(s\) for stage second", out)
    assert first and second, out
    wait_for(lambda: len(list(fake_dir.glob("started-*"))) == 2, "both stage-1 tasks in their cells", cluster=slurm,
             cfg=cfg)
    slurm.run("scancel", first.group(1))  # the whole stage-1 array: stage 2's afterany is met at once
    logs = cfg.paths.base / "runs" / "slurm-logs"
    wait_for(lambda: any(logs.glob(f"{second.group(1)}_*.log")) and not slurm.jobs(),
             "stage 2's task started and every task gone", cluster=slurm, cfg=cfg)
    stage_two = "".join(p.read_text() for p in logs.glob(f"{second.group(1)}_*.log"))
    assert "leaves them to stage first's workers" in stage_two, stage_two  # it started, and exited without work
    assert {r.state for r in rows(cfg)} == {PENDING} and all(r.coords["seed"] == 0 for r in rows(cfg)), rows(cfg)
    assert all(calls(r.cell_key) == 1 for r in rows(cfg))  # only stage 1's own tasks ever ran its cells

    (fake_dir / "release").touch()
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "slurm", *FAKE)  # watches to the end
    assert code == 0, out + err + task_logs(cfg)
    done = rows(cfg)
    first_done = max(r.finished_at for r in done if r.coords["seed"] == 0)
    assert [r.coords["seed"] for r in done].count(1) == 1
    assert all(r.claimed_at >= first_done for r in done if r.coords["seed"] == 1)  # stage 2 only after stage 1
    assert all(r.state == FINISHED for r in done) and runs_by_cell(cfg, None) == {r.cell_key: 1 for r in done}
    client = client_for(cfg)
    assert client.get_run(sweep_parent(client, cfg, experiment_id(client, cfg))).info.status == "FINISHED"


@pytest.mark.slow
def test_two_tasks_starting_together_on_a_new_experiment_lose_no_attempt_to_mlflows_dataset_race(
        slurm, make_config, tmp_path, pg_url, services):
    """Issue 37.1 as reported: two Slurm tasks start real training runs at once on a new experiment through the
    MLflow server on PostgreSQL; both log the same dataset inputs, and the server's read-then-insert lets one of
    them meet ``UniqueViolation "dataset_pk"`` (a 400). Made certain, as in test_dataset_race.py: the test holds
    the server's ``datasets`` table (reads go on, inserts wait) until both tasks wait on their insert. The loser's
    write is retried; both cells finish on their first attempt and no run FAILED."""
    import psycopg

    pg, _ = services
    cfg = cluster_project(make_config, tmp_path, pg_url, services, "race", steps=6, archs=("baseline", "lstm"),
                          runs={"timeout_s": 300, "busy_timeout_s": 300})  # a request may wait on the held table
    db = {"host": "127.0.0.1", "port": pg.port, "user": "postgres", "dbname": "mlflow"}
    waiting = ("SELECT count(*) FROM pg_stat_activity WHERE datname = 'mlflow' AND wait_event_type = 'Lock' "
               "AND query ILIKE '%INSERT INTO datasets%'")
    submitter = None
    try:
        with psycopg.connect(**db) as hold, psycopg.connect(**db, autocommit=True) as watch:
            hold.execute("LOCK TABLE datasets IN EXCLUSIVE MODE")  # SELECT goes on, INSERT waits
            submitter = watch_sweep(cfg, tmp_path)
            try:
                wait_for(lambda: watch.execute(waiting).fetchone()[0] >= 2 or submitter.poll() is not None,
                         "both tasks' dataset inserts waiting", limit=300, cfg=cfg)
                assert submitter.poll() is None, submitter.communicate()[0]
            finally:
                hold.rollback()  # the lock goes: one insert wins, the other meets its row
        finish(submitter, cfg)
    finally:
        if submitter is not None and submitter.poll() is None:
            submitter.kill()
    log = task_logs(cfg)
    assert 'MLflow store busy (log_inputs): BAD_REQUEST: (psycopg.errors.UniqueViolation) duplicate key value ' \
           'violates unique constraint "dataset_pk"; retrying' in log, log  # the race was lost, and retried
    assert {(r.state, r.attempts) for r in rows(cfg)} == {(FINISHED, 1)}, rows(cfg)
    assert runs_by_cell(cfg, "FAILED") == {} and runs_by_cell(cfg, None) == {r.cell_key: 1 for r in rows(cfg)}


def test_tune_runs_its_trials_as_slurm_array_tasks_and_sweep_cancel_stops_a_running_study(slurm, cli, make_config,
                                                                                        tmp_path, pg_url):
    """Issue 47, item 3: `tune --launcher slurm` submits array tasks that claim the study's trial rows (one Optuna
    trial per row, each row once) and watches them to the end; a study running on Slurm is stopped by `sweep cancel
    --study`: its tasks are scancelled, the running trial's row is given back, the watching `tune` exits 130."""
    import optuna

    from bronchocli.runs.parents import KIND_STUDY, find_parent
    from bronchocli.sweep.tuning import studies, trial as tuning
    from bronchocli.sweep.tuning.rows import study_sweep
    from bronchocli.sweep.summary import TAG_CANCELLED

    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=4, frames=8, image_size=32)
    cfg = make_config(storage=pg_url, archs=("baseline",), losses=("mse",),
                      sweep={"heartbeat_s": 0.5, "stale_after_s": 30.0, "poll_s": 0.2},
                      slurm={"cpus_per_task": 1, "shared_filesystem": True, "tasks": 2},
                      splits={"train": 2, "val": 1, "test": 1, "cross_subject_val": 1},
                      data={"window": 3, "cache_dir": "cache"},
                      train={"batch_size": 3, "steps": 6, "val_every": 3, "bn_recalibrate": 1, "threads": 1,
                             "max_val_pairs": 6},
                      tune={"startup_trials": 1, "warmup_validations": 0,
                            "space": {"train.lr": {"type": "float", "low": 1.0e-5, "high": 1.0e-3, "log": True}}})
    path = str(cfg.paths.base / "experiments.yaml")
    target = ["-a", "baseline", "-l", "mse", "-P", "personalized", "-q"]
    name = tuning.study_name(cfg, cfg.cell(arch="baseline", rot_loss="mse", population="personalized"))
    code, out, err = cli("tune", "-c", path, *target, "--trials", "3", "--launcher", "slurm")
    assert code == 0, out + err + task_logs(cfg)
    assert re.search(r"submitted Slurm array job \d+: 2 task\(s\) for stage trials", out), out
    store = SweepStore(cfg.paths.storage_url)
    trial_rows = store.rows(study_sweep(name))
    assert [r.state for r in trial_rows] == [FINISHED] * 3
    assert all(re.fullmatch(r"\S+:\d+ slurm \d+_\d+( gpu[01])?", r.worker) for r in trial_rows), trial_rows
    study = optuna.load_study(study_name=name, storage=studies.storage_for(cfg))
    trials = study.get_trials(deepcopy=False)
    assert len(trials) == 3 and studies.finished(study) == 3  # one trial per row, none twice
    assert sorted(r.run_id for r in trial_rows) == sorted(t.user_attrs[tuning.ATTR_RUN] for t in trials)
    client = client_for(cfg)
    parent = find_parent(client, experiment_id(client, cfg), KIND_STUDY, name)
    assert client.get_run(parent).info.status == "FINISHED"
    code, out, _ = cli("status", "-c", path, "--sweep", study_sweep(name))
    assert code == 0 and "Slurm task" in out and "trial 2 ·" in out and all(r.run_id in out for r in trial_rows), out

    # the same study, one trial more, a long one: cancelled while it trains
    tuner = subprocess.Popen([sys.executable, "-c", MAIN, "tune", "-c", path, *target, "--trials", "4", "--launcher",
                              "slurm", "--set", "train.steps=100000"], cwd=tmp_path, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(lambda: any(r.cell_key == "trial-0003" and r.state == "running" and r.run_id
                             for r in store.rows(study_sweep(name))), "the fourth trial training", cluster=slurm,
                 cfg=cfg)
        code, out, err = cli("sweep", "cancel", "-c", path, "--study", name, "--launcher", "slurm")
        assert code == 0 and "cancelled Slurm job(s)" in out, out + err
        out, _ = tuner.communicate(timeout=LIMIT)
    finally:
        if tuner.poll() is None:
            tuner.kill()
    assert tuner.returncode == 130 and "was cancelled" in out, out + task_logs(cfg)
    slurm.wait_idle_queue(LIMIT)
    assert [r.state for r in store.rows(study_sweep(name))] == [FINISHED] * 3 + [PENDING]  # given back
    run = client.get_run(parent)
    assert run.info.status == "KILLED" and TAG_CANCELLED in run.data.tags
    code, out, _ = cli("sweep", "cancel", "-c", path, "--study", name, "--launcher", "slurm")
    assert code == 0 and f"no Slurm job of sweep {study_sweep(name)} is queued or running" in out
