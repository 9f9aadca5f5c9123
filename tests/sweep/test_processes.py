"""Real worker processes on one sweep: exactly one FINISHED run per cell under races, SIGKILL and SIGINT."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from pathlib import Path

import pytest
from sweep_fakes import calls, fake_runner, runs_by_cell, wait_for

from bronchocli.runs.client import client_for
from bronchocli.runs.records import TAG_FAILURE
from bronchocli.sweep import FINISHED, PENDING, SweepStore, Worker, WorkerJob, prepare, worker_config
from bronchocli.sweep.launchers import LocalLauncher
from bronchocli.sweep.stagework import local_process


def start(cfg, plan, n: int, log_dir: Path, first: int = 0) -> list:
    """``n`` worker processes as the local launcher starts them: the one worker entry, each with its log."""
    wcfg = worker_config(cfg)
    procs = []
    for i in range(first, first + n):
        job = WorkerJob(wcfg, cfg.paths.storage_url, None, LocalLauncher, fake_runner, exit_when_idle=False,
                        ends_parent=False, log_path=str(log_dir / f"w{i}.log"), parent_pid=os.getpid(), cpu_workers=n)
        proc = mp.get_context("spawn").Process(target=local_process, args=(job, None))
        proc.start()
        procs.append(proc)
    return procs


def join(procs, log_dir: Path) -> list:
    for p in procs:
        p.join(120)
        if p.is_alive():
            p.kill()
    codes = [p.exitcode for p in procs]
    logs = "\n".join(f.read_text() for f in sorted(log_dir.glob("*.log")))
    return codes, logs


def assert_exactly_once(cfg, store, plan):
    keys = {c.key for c in plan.cells}
    finished = runs_by_cell(cfg, "FINISHED")
    assert finished == {k: 1 for k in keys}, "a cell without, or with more than one, FINISHED run"
    assert runs_by_cell(cfg, "RUNNING") == {}
    rows = store.rows(cfg.name)
    assert {r.cell_key: r.state for r in rows} == {k: FINISHED for k in keys}
    client = client_for(cfg)
    assert all(client.get_run(r.run_id).info.status == "FINISHED" for r in rows)


def test_three_workers_on_sqlite_run_every_cell_exactly_once(make_config, fake_dir, tmp_path):
    cfg = make_config(archs=("baseline", "lstm", "convlstm", "conv3d", "offsetnet"), losses=("mse", "de", "ce"))
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    procs = start(cfg, plan, 3, tmp_path)
    codes, logs = join(procs, tmp_path)
    assert codes == [0, 0, 0], logs
    assert_exactly_once(cfg, store, plan)
    assert [calls(c.key) for c in plan.cells] == [1] * 15  # no cell was even started twice


@pytest.mark.postgres
def test_four_workers_on_postgres_survive_a_sigkilled_worker(make_config, fake_dir, tmp_path, pg_url):
    cfg = make_config(storage=pg_url, archs=("baseline", "lstm", "convlstm", "conv3d", "offsetnet"),
                      losses=("mse", "ce"), sweep={"heartbeat_s": 0.5, "stale_after_s": 2.5})
    (fake_dir / "block-conv3d").touch()  # both conv3d cells wait for the gate, with their runs RUNNING
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    procs = start(cfg, plan, 4, tmp_path)
    wait_for(lambda: len(list(fake_dir.glob("started-*"))) == 2, "two workers inside conv3d cells", procs)
    victim_file = sorted(fake_dir.glob("started-*"))[0]
    victim_key, victim_pid = victim_file.name.split("-")[1], int(victim_file.name.split("-")[2])
    os.kill(victim_pid, signal.SIGKILL)
    (fake_dir / "release").touch()
    procs += start(cfg, plan, 1, tmp_path, first=4)  # a late worker joins
    codes, logs = join(procs, tmp_path)
    victim = next(p for p in procs if p.pid == victim_pid)
    assert victim.exitcode == -signal.SIGKILL
    assert sorted(c for p, c in zip(procs, codes) if p is not victim) == [0, 0, 0, 0], logs
    assert_exactly_once(cfg, store, plan)
    dead_run = client_for(cfg).get_run(victim_file.read_text())
    assert dead_run.info.status == "KILLED" and "lost" in dead_run.data.tags[TAG_FAILURE]
    row = next(r for r in store.rows(cfg.name) if r.cell_key == victim_key)
    assert row.attempts == 2 and calls(victim_key) == 2
    assert all(calls(c.key) == 1 for c in plan.cells if c.key != victim_key)
    store.close()


def test_sigint_releases_the_cell_and_a_rerun_resumes_only_what_is_left(make_config, fake_dir, tmp_path):
    cfg = make_config(archs=("baseline", "lstm"), grid_order=True)  # baseline claimed first, lstm interrupted
    (fake_dir / "block-lstm").touch()
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    base, lstm = plan.cells
    procs = start(cfg, plan, 1, tmp_path)
    wait_for(lambda: any(fake_dir.glob(f"started-{lstm.key}-*")), "the worker inside the lstm cell", procs)
    os.kill(procs[0].pid, signal.SIGINT)
    codes, logs = join(procs, tmp_path)
    assert codes == [130], logs
    rows = {r.cell_key: r for r in store.rows(cfg.name)}
    assert rows[base.key].state == FINISHED
    assert (rows[lstm.key].state, rows[lstm.key].attempts, rows[lstm.key].token) == (PENDING, 0, None)
    assert runs_by_cell(cfg, "KILLED") == {lstm.key: 1}
    killed = rows[lstm.key].run_id
    (fake_dir / "block-lstm").unlink()
    plan = prepare(cfg, store, dataset=False)  # the re-run
    assert Worker(cfg, plan.cells, store, fake_runner).run() == 0
    assert (calls(base.key), calls(lstm.key)) == (1, 2)
    assert_exactly_once(cfg, store, plan)
    assert next(r for r in store.rows(cfg.name) if r.cell_key == lstm.key).run_id == killed  # resumed, not redone
    assert runs_by_cell(cfg, "KILLED") == {}
