"""The worker loop in-process with fast fake runners: retries, claims lost mid-run, orphans of dead workers."""

from __future__ import annotations

import os

import pytest
from rich.console import Console
from sqlalchemy import update
from sweep_fakes import calls, fake_runner, runs_by_cell

from bronchocli.errors import MlflowUnreachable
from bronchocli.runs.client import MlflowBusy, client_for, experiment_id
from bronchocli.runs.contract import RunResult, resume_file
from bronchocli.runs.ownership import mark
from bronchocli.runs.records import TAG_FAILURE, TAG_KIND, cell_tags, search_runs
from bronchocli.sweep import FAILED, FINISHED, TAG_CLAIM, StorageError, SweepStore, Worker, prepare
from bronchocli.sweep.status import show_status
from bronchocli.sweep.storage import cells_table


def setup(cfg):
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    return store, plan


def rows(store, cfg):
    return {r.label.split("/")[0]: r for r in store.rows(cfg.name)}


def test_failed_cells_are_retried_automatically_up_to_max_retries(make_config, fake_dir):
    cfg = make_config(sweep={"max_retries": 1})
    (fake_dir / "fail-baseline").write_text("1")  # fails once, then succeeds
    store, plan = setup(cfg)
    assert Worker(cfg, plan.cells, store, fake_runner).run() == 0
    r = rows(store, cfg)
    assert (r["baseline"].state, r["baseline"].attempts) == (FINISHED, 2)
    assert (r["lstm"].state, r["lstm"].attempts) == (FINISHED, 1)
    base = r["baseline"].cell_key
    assert runs_by_cell(cfg, "FAILED") == {base: 1}
    assert runs_by_cell(cfg) == {c.key: 1 for c in plan.cells}


def test_without_retries_a_failure_stays_until_reset(make_config, fake_dir):
    cfg = make_config(sweep={"max_retries": 0})
    (fake_dir / "fail-baseline").write_text("1")
    store, plan = setup(cfg)
    assert Worker(cfg, plan.cells, store, fake_runner).run() == 0  # nothing left to run: the worker is done
    r = rows(store, cfg)
    assert (r["baseline"].state, r["baseline"].failure_reason) == (FAILED, "fake failure")
    again = prepare(cfg, store, dataset=False)  # a re-run does not retry it...
    assert again.state(next(c for c in again.cells if c.arch == "baseline")) == FAILED
    prepare(cfg, store, dataset=False, retry_failed=True)  # ...--retry-failed does
    Worker(cfg, plan.cells, store, fake_runner).run()
    assert rows(store, cfg)["baseline"].state == FINISHED
    assert runs_by_cell(cfg) == {c.key: 1 for c in plan.cells}


def test_a_runner_exception_fails_the_cell_with_its_reason(make_config, fake_dir):
    cfg = make_config(archs=("baseline",), sweep={"max_retries": 0})
    store, plan = setup(cfg)

    def broken(cfg, cell, **kw):
        raise ValueError("bad frame 7\nmore detail")

    Worker(cfg, plan.cells, store, broken).run()
    row = rows(store, cfg)["baseline"]
    assert (row.state, row.failure_reason, row.run_id) == (FAILED, "ValueError: bad frame 7", None)


def test_a_worker_that_lost_its_claim_kills_its_run_and_the_cell_is_run_once(make_config, fake_dir):
    """Mid-run the cell is taken over (as if this worker had looked dead); its FINISHED run must not count."""
    cfg = make_config(archs=("baseline",), sweep={"max_retries": 2})  # the thief's lost claim uses an attempt too
    store, plan = setup(cfg)
    lost_runs = []

    def hijacked(cfg, cell, run_id_callback=None, **kw):
        def callback(run_id):
            run_id_callback(run_id)
            if not lost_runs:  # first attempt: another worker steals the claim right after the run starts
                lost_runs.append(run_id)
                with store.engine.begin() as conn:
                    conn.execute(update(cells_table).values(heartbeat=cells_table.c.heartbeat - 1000))
                assert store.claim(cfg.name, [cell.key], "thief", max_retries=1, stale_after_s=2) is not None

        return fake_runner(cfg, cell, run_id_callback=callback, **kw)

    worker = Worker(cfg, plan.cells, store, hijacked)
    assert worker.run() == 0  # the thief never heartbeats: its claim goes stale and this worker takes it back
    assert worker.stats.lost == 1 and worker.stats.finished == 1
    client = client_for(cfg)
    lost = client.get_run(lost_runs[0])
    assert lost.info.status == "KILLED" and "lost its claim" in lost.data.tags[TAG_FAILURE]
    assert runs_by_cell(cfg) == {plan.cells[0].key: 1}
    row = store.rows(cfg.name)[0]
    assert row.state == FINISHED and row.run_id != lost_runs[0] and row.attempts == 3


def test_runs_left_by_a_dead_worker_are_killed_when_its_cells_are_taken_over_but_a_finished_one_is_recorded(
        make_config, fake_dir):
    cfg = make_config(archs=("baseline", "lstm"))
    store, plan = setup(cfg)
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    orphans = {}
    for cell in plan.cells:
        claim = store.claim(cfg.name, [cell.key], "dead:1", max_retries=1, stale_after_s=60)
        run = client.create_run(exp, tags=cell_tags(cfg, cell, **{TAG_CLAIM: claim.token}))
        orphans[cell.arch] = run.info.run_id
        if cell.arch == "lstm":  # died after finishing its run, before recording it on the row
            store.set_run_id(claim.token, run.info.run_id)
            client.set_terminated(run.info.run_id, "FINISHED")
        # baseline: died right after creating the run (the row never learnt its id)
    with store.engine.begin() as conn:
        conn.execute(update(cells_table).values(heartbeat=cells_table.c.heartbeat - 1000))
    assert Worker(cfg, plan.cells, store, fake_runner).run() == 0
    killed = client.get_run(orphans["baseline"])
    assert killed.info.status == "KILLED" and "dead:1 lost" in killed.data.tags[TAG_FAILURE]
    assert client.get_run(orphans["lstm"]).info.status == "FINISHED"  # the result is kept, not trained again
    r = rows(store, cfg)
    assert (r["lstm"].state, r["lstm"].run_id) == (FINISHED, orphans["lstm"])
    assert r["baseline"].state == FINISHED and r["baseline"].run_id != orphans["baseline"]
    assert runs_by_cell(cfg) == {c.key: 1 for c in plan.cells}
    assert calls(r["lstm"].cell_key) == 0 and calls(r["baseline"].cell_key) == 1


@pytest.mark.parametrize("attempts_left", [True, False])
def test_a_running_row_whose_run_finished_is_recorded_done_even_on_its_last_attempt(make_config, fake_dir,
                                                                                   attempts_left):
    """A worker killed between ending its run FINISHED and writing the row: whoever takes the stale claim over
    records that run for the cell (never KILLED, never trained again), also when no attempt is left."""
    cfg = make_config(archs=("baseline",), sweep={"max_retries": 1 if attempts_left else 0})
    store, plan = setup(cfg)
    cell, client = plan.cells[0], client_for(cfg)
    claim = store.claim(cfg.name, [cell.key], "dead:1", max_retries=1, stale_after_s=60)
    run_id = client.create_run(experiment_id(client, cfg), tags=cell_tags(cfg, cell, **{TAG_CLAIM: claim.token})
                               ).info.run_id
    store.set_run_id(claim.token, run_id)
    client.set_terminated(run_id, "FINISHED")
    with store.engine.begin() as conn:
        conn.execute(update(cells_table).values(heartbeat=cells_table.c.heartbeat - 1000))
    worker = Worker(cfg, plan.cells, store, fake_runner)
    assert worker.run() == 0 and worker.stats.finished == 1
    row = store.rows(cfg.name)[0]
    assert (row.state, row.run_id) == (FINISHED, run_id) and client.get_run(run_id).info.status == "FINISHED"
    assert calls(cell.key) == 0 and runs_by_cell(cfg, None) == {cell.key: 1}


def test_a_worker_that_cannot_record_a_finished_run_keeps_it_and_the_next_sweep_records_it(
        make_config, fake_dir, monkeypatch):
    cfg = make_config(archs=("baseline",), sweep={"heartbeat_s": 0.1, "stale_after_s": 0.3})
    store, plan = setup(cfg)
    cell = plan.cells[0]

    def full(*args, **kw):
        raise StorageError("sweep storage sqlite:///runs/sweep.db: database or disk is full")

    with monkeypatch.context() as m, pytest.raises(StorageError) as err:
        m.setattr(store, "finish", full)
        Worker(cfg, plan.cells, store, fake_runner).run()
    (run_id,) = _cell_runs(cfg)
    assert str(err.value) == (f"cell {cell.label}: run {run_id} FINISHED, but its claims row could not be written "
                              "(sweep storage sqlite:///runs/sweep.db: database or disk is full); the run stays "
                              "FINISHED and the next sweep records it for its cell (not trained again)")
    assert runs_by_cell(cfg, "FINISHED") == {cell.key: 1} and store.rows(cfg.name)[0].state == "running"
    # the disk has room again; the dead worker's claim has gone stale
    with store.engine.begin() as conn:
        conn.execute(update(cells_table).values(heartbeat=cells_table.c.heartbeat - 1000))
    again = prepare(cfg, store, dataset=False)
    assert Worker(cfg, again.cells, store, fake_runner).run() == 0
    row = store.rows(cfg.name)[0]
    assert (row.state, row.run_id) == (FINISHED, run_id) and calls(cell.key) == 1  # trained once, recorded
    assert runs_by_cell(cfg, None) == {cell.key: 1}


def _cell_runs(cfg):
    client = client_for(cfg)
    return [r.info.run_id for r in search_runs(client, [experiment_id(client, cfg)], {TAG_KIND: "cell"})]


def test_a_stop_that_arrived_while_the_run_was_evaluating_is_obeyed_after_recording_it(make_config, fake_dir):
    import signal
    from dataclasses import replace

    cfg = make_config(archs=("baseline", "lstm"))
    store, plan = setup(cfg)

    def stopped_during_evaluation(cfg, cell, **kw):
        return replace(fake_runner(cfg, cell, **kw), stop_requested=signal.SIGTERM)

    assert Worker(cfg, plan.cells, store, stopped_during_evaluation).run() == 130
    states = sorted(r.state for r in store.rows(cfg.name))
    assert states.count(FINISHED) == 1  # the finished run is recorded, and no further cell is started
    assert len(runs_by_cell(cfg)) == 1


# -- the machine failed the run: busy database, full disk (issue 22, items 2, 3, 6) ------------------------------


def machine_failure(error_type, ckpt: bool = True):
    """A runner whose run fails with ``error_type`` (after writing a checkpoint), and succeeds when resumed."""
    from bronchocli.runs.contract import RunResult, resume_file

    seen = []

    def runner(cfg, cell, *, resume=None, extra_tags=None, run_id_callback=None, **_):
        client = client_for(cfg)
        if resume:
            seen.append(("resumed", resume))
            client.update_run(resume, "RUNNING")
            run_id_callback(resume)
            client.set_terminated(resume, "FINISHED")
            return RunResult(resume, "FINISHED", {"pair.pos_l2.mean": 1.0})
        exp = experiment_id(client, cfg)
        run_id = client.create_run(exp, tags=cell_tags(cfg, cell, **(extra_tags or {}))).info.run_id
        run_id_callback(run_id)
        if ckpt:
            mark(resume_file(cfg, run_id).parent, run_id, cell.key)  # as checkpoint.save does
            resume_file(cfg, run_id).write_text("checkpoint")
        seen.append(("failed", run_id))
        client.set_tag(run_id, TAG_FAILURE, f"{error_type.__name__}: the machine")
        client.set_terminated(run_id, "FAILED")
        raise error_type("the machine")

    return runner, seen


def test_a_busy_database_releases_the_cell_without_using_an_attempt_and_the_retry_resumes(make_config, fake_dir):
    cfg = make_config(archs=("baseline",), sweep={"max_retries": 0})
    store, plan = setup(cfg)
    runner, seen = machine_failure(MlflowBusy)
    assert Worker(cfg, plan.cells, store, runner).run() == 0
    row = rows(store, cfg)["baseline"]
    assert (row.state, row.attempts) == (FINISHED, 1)  # with max_retries 0: the busy attempt did not count
    assert [s[0] for s in seen] == ["failed", "resumed"] and seen[0][1] == seen[1][1]


def test_a_full_disk_fails_the_cell_with_its_reason_and_the_retry_resumes_the_checkpoint(make_config, fake_dir):
    from bronchocli.training.checkpoint import CheckpointWriteError

    cfg = make_config(archs=("baseline",), sweep={"max_retries": 0})
    store, plan = setup(cfg)
    runner, seen = machine_failure(CheckpointWriteError)
    with pytest.raises(CheckpointWriteError):  # a full disk meets every cell: the worker stops (issue 37.3)
        Worker(cfg, plan.cells, store, runner).run()
    row = rows(store, cfg)["baseline"]
    assert row.state == FAILED and row.failure_reason == "CheckpointWriteError: the machine"
    assert (cfg.paths.checkpoints / seen[0][1]).exists()  # kept: the machine failed, not the cell
    assert Worker(cfg, plan.cells, store, runner).run() == 0  # space freed, the same command: resumed once
    assert rows(store, cfg)["baseline"].state == FINISHED
    assert [s[0] for s in seen] == ["failed", "resumed"] and seen[0][1] == seen[1][1]


def test_a_failed_run_keeps_its_checkpoint_only_while_its_cell_can_be_retried(make_config, fake_dir):
    from bronchocli.training.loop import NonFiniteLoss

    cfg = make_config(archs=("baseline",), sweep={"max_retries": 0})
    store, plan = setup(cfg)
    runner, seen = machine_failure(NonFiniteLoss)  # the cell's own failure: its attempt is spent
    assert Worker(cfg, plan.cells, store, runner).run() == 0
    row = rows(store, cfg)["baseline"]
    assert row.state == FAILED and row.failure_reason == "NonFiniteLoss: the machine"
    assert not (cfg.paths.checkpoints / seen[0][1]).exists()  # last attempt: nothing will resume it


# -- a worker killed hard (kill -9, OOM) mid-cell (issue 30, item 2) ------------------------------------------


def test_a_dead_workers_cell_shows_stale_and_is_resumed_from_its_checkpoint_by_whoever_takes_it_over(
        make_config, fake_dir):
    cfg = make_config(archs=("baseline",), sweep={"max_retries": 1, "stale_after_s": 30})
    store, plan = setup(cfg)
    (cell,) = plan.cells
    client = client_for(cfg)
    claim = store.claim(cfg.name, [cell.key], "node1:4242 slurm 7_0", max_retries=1, stale_after_s=30)
    run_id = client.create_run(experiment_id(client, cfg), tags=cell_tags(cfg, cell, **{TAG_CLAIM: claim.token})
                               ).info.run_id
    store.set_run_id(claim.token, run_id)
    ckpt = resume_file(cfg, run_id)
    ckpt.parent.mkdir(parents=True)
    ckpt.write_text("step 18 of 24")  # its last checkpoint; then kill -9: the run stays RUNNING

    def status() -> str:
        console = Console(width=250, record=True)
        show_status(cfg, store, cfg.name, False, console)
        return console.export_text()

    assert "running 1" in status() and "stale" not in status()  # heartbeat fresh: alive as far as anyone knows
    with store.engine.begin() as conn:
        conn.execute(update(cells_table).values(heartbeat=cells_table.c.heartbeat - 31))
    shown = status()
    assert "stale (worker lost" in shown and "running 0" in shown and "stale 1" in shown, shown

    seen = []

    def runner(cfg, cell, *, resume=None, extra_tags=None, run_id_callback=None, **_):
        seen.append((resume, ckpt.is_file() and ckpt.read_text()))
        client.update_run(resume, "RUNNING")
        run_id_callback(resume)
        client.set_terminated(resume, "FINISHED")
        return RunResult(resume, "FINISHED", {"pair.pos_l2.mean": 1.0})

    assert Worker(cfg, plan.cells, store, runner).run() == 0
    assert seen == [(run_id, "step 18 of 24")]  # resumed, its checkpoint there when the runner started
    assert runs_by_cell(cfg, "FINISHED") == {cell.key: 1} and runs_by_cell(cfg, None) == {cell.key: 1}
    (row,) = store.rows(cfg.name)
    assert (row.state, row.run_id) == (FINISHED, run_id)


def test_a_takeover_keeps_the_lost_runs_link_until_the_new_claim_names_its_run(make_config, fake_dir):
    cfg = make_config(archs=("baseline",))
    store, plan = setup(cfg)
    (cell,) = plan.cells
    first = store.claim(cfg.name, [cell.key], "dead:1", max_retries=2, stale_after_s=30)
    store.set_run_id(first.token, "run-of-the-dead")
    with store.engine.begin() as conn:
        conn.execute(update(cells_table).values(heartbeat=cells_table.c.heartbeat - 31))
    second = store.claim(cfg.name, [cell.key], "alive:2", max_retries=2, stale_after_s=30)
    assert second.previous.worker == "dead:1" and second.released_run == "run-of-the-dead"
    (row,) = store.rows(cfg.name)
    assert row.run_id == "run-of-the-dead"  # sweep --gc sees the cell running with it: its checkpoint is needed


# -- the MLflow store went away mid-cell (issue 30, item 3) -------------------------------------------------------


def test_an_unreachable_store_releases_the_cell_without_an_attempt_and_the_run_is_marked_when_it_answers(
        make_config, fake_dir, monkeypatch):
    cfg = make_config(archs=("baseline",), sweep={"max_retries": 0, "poll_s": 0.01})
    store, plan = setup(cfg)
    client = client_for(cfg)
    made = []

    def runner(cfg, cell, *, resume=None, extra_tags=None, run_id_callback=None, **_):
        run_id = client.create_run(experiment_id(client, cfg), tags=cell_tags(cfg, cell, **extra_tags)).info.run_id
        run_id_callback(run_id)
        made.append(run_id)
        if len(made) == 1:  # the store went away mid-run: the run could not even be marked (left RUNNING)
            raise MlflowUnreachable("runs.uri http://mlflow:5000: no answer within 10 s")
        client.set_terminated(run_id, "FINISHED")
        return RunResult(run_id, "FINISHED", {"pair.pos_l2.mean": 1.0})

    worker = Worker(cfg, plan.cells, store, runner)
    raw = worker.client.raw
    real, outage = raw.set_terminated, [True]

    def set_terminated(run_id, status=None, **kw):  # still away when the worker first tries to mark it
        if outage.pop() if outage else False:
            raise RuntimeError("API request failed: Max retries exceeded (too many 503 error responses)")
        return real(run_id, status, **kw)

    monkeypatch.setattr(raw, "set_terminated", set_terminated)
    assert worker.run() == 0
    (row,) = store.rows(cfg.name)
    assert (row.state, row.attempts, row.run_id) == (FINISHED, 1, made[1])  # with max_retries 0: no attempt used
    first = client.get_run(made[0])
    assert first.info.status == "FAILED" and "MlflowUnreachable" in first.data.tags[TAG_FAILURE]  # not RUNNING
    assert runs_by_cell(cfg, "RUNNING") == {} and runs_by_cell(cfg, "FINISHED") == {row.cell_key: 1}


def test_a_claim_is_held_through_a_database_outage_only_while_nobody_can_have_taken_it_over(monkeypatch):
    from bronchocli.sweep import liveness
    from bronchocli.sweep.liveness import Heartbeat, StopSignals
    from bronchocli.sweep.storage import StorageError

    class Store:
        answer: bool | None = True  # None: the claims database is away

        def heartbeat(self, token):
            if self.answer is None:
                raise StorageError("could not connect")
            return self.answer

    now = [100.0]
    monkeypatch.setattr(liveness.time, "monotonic", lambda: now[0])
    store = Store()
    hb = Heartbeat(store, "t", 1.0, lambda: None, StopSignals(), lease_s=60.0)
    assert hb.holds()  # renewed at 100
    store.answer, now[0] = None, 140.0
    assert hb.holds()  # 40 s without the database: nobody can have taken it over yet
    now[0] = 150.0
    assert not hb.holds()  # 50 s: near the cut-off, another worker may have
    store.answer = True
    assert hb.holds() and not hb.lost  # back: renewed
    store.answer = False
    assert not hb.holds() and hb.lost  # taken over: for good
    store.answer = True
    assert not hb.holds()


def test_a_worker_stopped_on_an_error_has_its_error_on_the_sweeps_console(tmp_path):
    """The one line a worker's log ends on (``stagework.exit_process``) reaches the console of the command that
    started it, not only "1 worker(s) stopped on an error"."""
    from bronchocli.sweep.planview import report_workers

    line = ("cell baseline/mse: run abc FINISHED, but its claims row could not be written (disk full); the run stays "
            "FINISHED and the next sweep records it for its cell (not trained again)")
    (tmp_path / f"node-{os.getpid()}-w0.log").write_text(
        "2024-01-01 10:00:00,000 node:77 INFO bronchocli.sweep.worker: claimed baseline/mse\n"
        f"2024-01-01 10:00:09,000 node:77 ERROR bronchocli.sweep.stagework: {line}\n")
    (tmp_path / f"node-{os.getpid()}-w1.log").write_text("2024-01-01 10:00:00,000 node:78 INFO x: done\n")
    (tmp_path / f"node-{os.getpid() + 1}-w0.log").write_text("2024 node:9 ERROR x: another command's worker\n")
    console = Console(record=True, width=300)
    report_workers(console, [2, 0], tmp_path)
    out = console.export_text()
    assert "1 worker(s) stopped on an error" in out and f"  {line}\n" in out and "another command" not in out
