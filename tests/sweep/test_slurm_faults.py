"""The Slurm watcher's arithmetic after faults, without a cluster (squeue, sbatch, scontrol stood in for):
array sizes, dependencies of a re-submit, a dead task's claim, requeued tasks' hold (issue 30, item 4)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from rich.console import Console
from sqlalchemy import update

from bronchocli.sweep import PENDING, SweepStore, prepare
from bronchocli.sweep import launch
from bronchocli.sweep.launchers import Workers
from bronchocli.sweep.launchers import slurm as launcher
from bronchocli.sweep.launchers.slurm import SlurmLauncher, job_name, release_held
from bronchocli.sweep.plan import StageWalk
from bronchocli.sweep.storage import cells_table


def Task(task: str, job: str, state: str, stage: str, count: int, reason: str = "") -> Workers:  # noqa: N802
    """A line of squeue as the Slurm launcher reads it."""
    return Workers(task, job, state, stage, count, reason, ending=state in launcher.ENDING)


def submit_missing(walk, command, console):
    return launch.submit_missing(walk, SlurmLauncher(walk.cfg, command), console)


class FakeSlurm:
    """squeue answers ``active``; sbatch hands out job ids 100, 101, ...; every scontrol call is recorded."""

    def __init__(self, monkeypatch, active=()):
        self.active, self.submitted, self.scontrol = list(active), [], []
        monkeypatch.setattr(launcher, "sweep_tasks", lambda cfg: list(self.active))
        monkeypatch.setattr(launcher, "submit", self.submit)
        monkeypatch.setattr(launcher, "_run", self.run)

    def submit(self, cfg, stage, tasks, command, dependency=()):
        job = str(100 + len(self.submitted))
        self.submitted.append((job, stage, tasks, tuple(dependency)))
        return job

    def run(self, args, what):
        assert args[0] == "scontrol", args
        self.scontrol.append(args[1:])
        return ""


def two_stages(make_config, **slurm):
    stages = [{"name": "first"}, {"name": "second", "grid": {"seed": [1]}, "select": {"top": 1, "over": ["arch"]}}]
    return make_config(archs=("baseline", "lstm", "convlstm"), stages=stages, slurm=slurm,
                       sweep={"stale_after_s": 30.0, "max_retries": 1})


def walk_of(cfg):
    store = SweepStore(cfg.paths.storage_url)
    prepare(cfg, store, dataset=False)
    return StageWalk(cfg, store), store


def quiet() -> Console:
    return Console(file=open("/dev/null", "w"))  # noqa: SIM115 - closed with the process


def test_a_resubmitted_earlier_stage_is_added_to_the_queued_later_stages_dependency(make_config, monkeypatch):
    cfg = two_stages(make_config)
    walk, store = walk_of(cfg)
    # stage 1's array was cancelled (its cells pending again); stage 2's array still waits in the queue
    slurm = FakeSlurm(monkeypatch, [Task("20_[0]", "20", "PENDING", "second", 1, "Dependency")])
    submit_missing(walk, ["python"], quiet())
    assert slurm.submitted == [("100", "first", 3, ())]
    assert slurm.scontrol == [["update", "JobId=20", "Dependency=afterany:100"]]  # stage 2 waits for it too


def test_arrays_are_no_larger_than_the_tasks_that_can_run_at_once(make_config, monkeypatch):
    cfg = two_stages(make_config, array_parallelism=2)
    walk, store = walk_of(cfg)
    slurm = FakeSlurm(monkeypatch)
    submit_missing(walk, ["python"], quiet())
    # 3 cells, 2 tasks at once: each task loops over cells, a third would start after the work is done
    assert slurm.submitted == [("100", "first", 2, ()), ("101", "second", 1, ("100",))]
    cfg = two_stages(make_config, tasks=1)
    slurm = FakeSlurm(monkeypatch)
    submit_missing(StageWalk(cfg, store), ["python"], quiet())
    assert [s[2] for s in slurm.submitted] == [1, 1]


def test_a_dead_tasks_cell_gets_a_task_only_once_its_claim_is_stale(make_config, monkeypatch):
    cfg = two_stages(make_config)
    walk, store = walk_of(cfg)
    keys = [c.key for c in walk.cells(walk.stages[0])]
    for key, worker in zip(keys, ("n:1 slurm 7_0", "n:2 slurm 7_1", "n:3 slurm 7_2")):
        store.claim(cfg.name, [key], worker, max_retries=1, stale_after_s=30)
    for row in store.rows(cfg.name)[:2]:  # two of them finish; the third task was killed (kill -9): still RUNNING
        store.finish(row.token, f"run-{row.cell_key}", 1.0)
    slurm = FakeSlurm(monkeypatch)  # no task of the sweep is left
    assert submit_missing(walk, ["python"], quiet()) == []  # before the cut-off: a task would find nothing
    with store.engine.begin() as conn:
        conn.execute(update(cells_table).values(heartbeat=cells_table.c.heartbeat - 31))
    submit_missing(walk, ["python"], quiet())
    assert slurm.submitted[0][1:3] == ("first", 1)  # now claimable: one task takes it over


def test_a_live_tasks_cell_is_counted_as_covered(make_config, monkeypatch):
    cfg = two_stages(make_config)
    walk, store = walk_of(cfg)
    key = walk.cells(walk.stages[0])[0].key
    store.claim(cfg.name, [key], "n:1 slurm 7_0", max_retries=1, stale_after_s=30)
    slurm = FakeSlurm(monkeypatch, [Task("7_0", "7", "RUNNING", "first", 1)])
    submit_missing(walk, ["python"], quiet())
    assert slurm.submitted[0][1:4] == ("first", 2, ())  # three cells: one held by the live task, two more tasks


def test_a_requeued_task_is_started_after_a_few_seconds_not_after_slurms_hold(monkeypatch):
    calls = []
    monkeypatch.setattr(launcher, "_run", lambda args, what: calls.append(args[1:]) or "")
    held: dict[str, float] = {}
    tasks = [Task("7_1", "7", "PENDING", "first", 1, "BeginTime"), Task("7_2", "7", "PENDING", "first", 1, "None")]
    release_held(tasks, held, settle_s=3600)
    assert calls == [] and set(held) == {"7_1"}  # seen; too early (the killed instance's credential)
    release_held(tasks, held, settle_s=0)
    assert calls == [["update", "JobId=7_1", "StartTime=now"]]
    release_held(tasks[1:], held, settle_s=0)
    assert held == {}  # started: forgotten


def test_the_job_name_does_not_double_its_prefix():
    assert job_name("bronchopose-cpu") == "bronchopose-cpu" and job_name("t") == "bronchopose-t"


def test_the_workers_interpreter_and_its_venv_must_be_on_a_shared_path(make_config, monkeypatch, tmp_path):
    monkeypatch.setattr("shutil.which", lambda name: "/usr/bin/" + name)
    shared = {"storage": "postgresql://u@db.example/sweeps"}
    runs = {"uri": "http://mlflow.example:5000", "artifacts": "/srv/a", "checkpoints": "/srv/ck"}
    venv = Path("/tmp/node-venv")
    with pytest.raises(Exception, match="sweep.launchers.slurm.python /tmp/node-venv/bin/python: a node-local folder"):
        launcher.check(make_config(**shared, runs=runs, dataset={"root": "/srv/data"},
                                   slurm={"python": str(venv / "bin" / "python"), "logs": "/srv/logs"}))
    monkeypatch.setattr(sys, "executable", "/tmp/x/bin/python")
    with pytest.raises(Exception,
                       match="the Python running bronchopose .sweep.launchers.slurm.python. /tmp/x/bin/python"):
        launcher.check(make_config(**shared, runs=runs, dataset={"root": "/srv/data"}, slurm={"logs": "/srv/logs"}))


def test_the_task_that_finds_the_sweep_done_ends_its_parent_run(make_config, fake_dir):
    from sweep_fakes import fake_runner

    from bronchocli.cells import parse_only
    from bronchocli.runs.client import client_for, experiment_id
    from bronchocli.runs.parents import sweep_parent
    from bronchocli.sweep.task import run_task as run_one

    cfg = make_config(archs=("baseline",))
    store = SweepStore(cfg.paths.storage_url)
    prepare(cfg, store, dataset=False)
    client = client_for(cfg)
    parent = sweep_parent(client, cfg, experiment_id(client, cfg))
    assert client.get_run(parent).info.status == "RUNNING"
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0  # a detached sweep: no watcher
    assert client.get_run(parent).info.status == "FINISHED"


def test_a_task_stops_after_the_stage_its_array_was_submitted_for(make_config, fake_dir, monkeypatch):
    """A stage-1 task still alive when stage 1 ends must not take stage 2's cells: stage 2 has its own array, sized
    to its cells, whose tasks would then start to find nothing (issue 30, item 4). Without a stage it goes on."""
    from sweep_fakes import fake_runner

    from bronchocli.cells import parse_only
    from bronchocli.sweep.task import run_task as run_one

    cfg = two_stages(make_config)
    for arch, val in (("baseline", 3.0), ("lstm", 1.0), ("convlstm", 2.0)):
        (fake_dir / f"val-{arch}-mse").write_text(str(val))
    store = SweepStore(cfg.paths.storage_url)
    prepare(cfg, store, dataset=False)
    monkeypatch.setenv(launcher.STAGE_ENV, "first")
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    rows = store.rows(cfg.name)
    assert sorted(r.coords["seed"] for r in rows) == [0, 0, 0] and {r.state for r in rows} == {"finished"}
    monkeypatch.setenv(launcher.STAGE_ENV, "second")  # stage 2's task: the selection, then its cell
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    second = [r for r in store.rows(cfg.name) if r.coords["seed"] == 1]
    assert [(r.coords["arch"], r.state) for r in second] == [("lstm", "finished")]
    monkeypatch.setenv(launcher.STAGE_ENV, "third")
    with pytest.raises(Exception, match="submitted for stage 'third', which the config's stages no longer have"):
        run_one(cfg, parse_only([]), fake_runner, "slurm")


def test_a_later_stage_without_tasks_gets_its_array_though_earlier_stage_tasks_are_still_alive(
        make_config, fake_dir, monkeypatch):
    from sweep_fakes import fake_runner

    from bronchocli.cells import parse_only
    from bronchocli.sweep.task import run_task as run_one

    cfg = two_stages(make_config)
    walk, store = walk_of(cfg)
    monkeypatch.setenv(launcher.STAGE_ENV, "first")
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    # stage 1 is done; its last task has not left the queue yet, and stage 2 has no array (cancelled)
    slurm = FakeSlurm(monkeypatch, [Task("7_0", "7", "COMPLETING", "first", 1)])
    submit_missing(walk, ["python"], quiet())
    assert slurm.submitted == [("100", "second", 1, ())]  # the stage-1 task stops after stage 1: not counted


def test_a_cancelled_task_still_listed_as_completing_covers_no_cell(make_config, monkeypatch):
    """`scancel` then the submit command at once: the cancelled task is still in squeue (COMPLETING) while its
    cell is pending again; it must not count as the cell's task (the real-Slurm test once found "nothing new")."""
    cfg = two_stages(make_config)
    walk, store = walk_of(cfg)
    keys = [c.key for c in walk.cells(walk.stages[0])]
    for key, task in zip(keys[:2], ("7_0", "7_1")):
        store.claim(cfg.name, [key], f"n:1 slurm {task}", max_retries=1, stale_after_s=30)
    slurm = FakeSlurm(monkeypatch, [Task("7_0", "7", "RUNNING", "first", 1), Task("7_1", "7", "RUNNING", "first", 1),
                                    Task("7_2", "7", "COMPLETING", "first", 1),
                                    Task("8_[0]", "8", "PENDING", "second", 1, "Dependency")])
    submit_missing(walk, ["python"], quiet())
    assert slurm.submitted == [("100", "first", 1, ())]  # the released cell gets a task
    assert slurm.scontrol == [["update", "JobId=8", "Dependency=afterany:100:7"]]  # and stage 2 waits for it


def test_a_later_stages_task_that_finds_an_earlier_stage_unfinished_takes_none_of_its_cells(make_config, fake_dir,
                                                                                             monkeypatch):
    """Issue 37, item 3: stage 1's array cancelled, stage 2's (afterany) starts before the re-submitted stage 1: its
    tasks exit at once instead of running stage 1's cells on resources sized for stage 2."""
    from sweep_fakes import calls, fake_runner

    from bronchocli.cells import parse_only
    from bronchocli.sweep.task import run_task as run_one

    cfg = two_stages(make_config)
    walk, store = walk_of(cfg)
    first = walk.cells(walk.stages[0])
    store.claim(cfg.name, [first[0].key], "n:1 slurm 7_0", max_retries=1, stale_after_s=30)  # one still running
    monkeypatch.setenv(launcher.STAGE_ENV, "second")
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    rows = {r.cell_key: r for r in store.rows(cfg.name)}
    assert [calls(c.key) for c in first] == [0, 0, 0] and rows[first[0].key].worker == "n:1 slurm 7_0"
    assert [rows[c.key].state for c in first[1:]] == ["pending", "pending"]
    monkeypatch.setenv(launcher.STAGE_ENV, "first")  # stage 1's own task takes them
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    assert [calls(c.key) for c in first] == [0, 1, 1]


def _parent(cfg):
    from bronchocli.runs.client import client_for, experiment_id
    from bronchocli.runs.parents import sweep_parent

    client = client_for(cfg)
    parent = sweep_parent(client, cfg, experiment_id(client, cfg))
    client.update_run(parent, "RUNNING")  # as `sweep run --launcher slurm --detach` leaves it
    return client, parent


def test_the_last_task_to_leave_a_detached_sweep_unfinished_ends_its_parent_killed_and_a_new_task_reopens_it(
        make_config, fake_dir, monkeypatch):
    """Issue 50: `sweep run --detach`, then `scancel` of stage 1: stage 2's task starts (afterany), takes none of stage
    1's cells and leaves; nothing else would end the sweep's parent run, which stayed RUNNING until the next run."""
    from sweep_fakes import calls, fake_runner

    from bronchocli.cells import parse_only
    from bronchocli.sweep.summary import TAG_STOPPED
    from bronchocli.sweep.task import run_task as run_one

    cfg = two_stages(make_config)
    for arch, val in (("baseline", 3.0), ("lstm", 1.0), ("convlstm", 2.0)):
        (fake_dir / f"val-{arch}-mse").write_text(str(val))
    walk, store = walk_of(cfg)
    client, parent = _parent(cfg)
    slurm = FakeSlurm(monkeypatch, [Task("8_0", "8", "RUNNING", "second", 1)])  # this task, as squeue lists it
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "8")
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "0")
    monkeypatch.setenv(launcher.STAGE_ENV, "second")
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    run = client.get_run(parent)
    assert run.info.status == "KILLED", run.info
    assert run.data.tags[TAG_STOPPED] == (
        "no Slurm task of sweep t is queued or running and 3 cell(s) are not done (its tasks were stopped: `scancel`, "
        "a node gone); `bronchopose sweep run` resumes it")
    assert {r.state for r in store.rows(cfg.name)} == {PENDING} and not slurm.submitted

    slurm.active = [Task("9_0", "9", "RUNNING", "first", 1), Task("10_[0]", "10", "PENDING", "second", 1, "Dependency")]
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "9")
    monkeypatch.setenv(launcher.STAGE_ENV, "first")  # a task started on it again (a requeue, a submission by hand)
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    run = client.get_run(parent)
    assert run.info.status == "RUNNING" and TAG_STOPPED not in run.data.tags  # stage 2's task is still queued
    assert [calls(c.key) for c in walk.cells(walk.stages[0])] == [1, 1, 1]

    slurm.active = [Task("10_0", "10", "RUNNING", "second", 1)]
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "10")
    monkeypatch.setenv(launcher.STAGE_ENV, "second")
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    run = client.get_run(parent)
    assert run.info.status == "FINISHED" and TAG_STOPPED not in run.data.tags


def test_a_task_leaving_while_another_task_of_the_sweep_is_queued_or_a_cell_runs_elsewhere_leaves_the_parent_running(
        make_config, fake_dir, monkeypatch):
    from sweep_fakes import fake_runner

    from bronchocli.cells import parse_only
    from bronchocli.sweep.task import run_task as run_one

    cfg = two_stages(make_config)
    walk, store = walk_of(cfg)
    client, parent = _parent(cfg)
    monkeypatch.setenv(launcher.STAGE_ENV, "second")
    FakeSlurm(monkeypatch, [Task("7_[0-2]", "7", "PENDING", "first", 3, "Priority")])  # stage 1 still queued
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    assert client.get_run(parent).info.status == "RUNNING"
    FakeSlurm(monkeypatch, [Task("7_0", "7", "COMPLETING", "first", 1)])  # being cancelled: not a worker any more
    first = walk.cells(walk.stages[0])
    claim = store.claim(cfg.name, [first[0].key], "n:1", max_retries=1, stale_after_s=30)  # a worker run by hand
    assert claim is not None
    assert run_one(cfg, parse_only([]), fake_runner, "slurm") == 0
    assert client.get_run(parent).info.status == "RUNNING"  # that worker ends the sweep


def test_status_ends_the_parent_of_a_detached_sweep_whose_tasks_all_went_before_any_ran(make_config, monkeypatch):
    """Every task cancelled while still pending: none ran to end the parent; `status --repair` does (settle_detached),
    and `status` says so in one line.
    A sweep whose watcher lives here, or with a task still queued, is left RUNNING."""
    from bronchocli.sweep.entry import settle_detached
    from bronchocli.sweep.status import stopped_line
    from bronchocli.sweep.summary import TAG_LAUNCHER, TAG_WATCHER, reopen, watcher_tag

    cfg = two_stages(make_config)
    walk, store = walk_of(cfg)
    client, parent = _parent(cfg)
    client.set_tag(parent, TAG_LAUNCHER, "slurm")  # as `sweep run --launcher slurm --detach` tags it
    client.set_tag(parent, TAG_WATCHER, watcher_tag(detached=True))
    slurm = FakeSlurm(monkeypatch, [Task("7_[0-2]", "7", "PENDING", "first", 3, "Priority")])
    assert settle_detached(cfg, store) is None and client.get_run(parent).info.status == "RUNNING"
    assert stopped_line(cfg, cfg.name) is None
    slurm.active = []  # scancel while they were pending
    client.set_tag(parent, TAG_WATCHER, watcher_tag(detached=False))  # a watcher in this (live) process
    assert settle_detached(cfg, store) is None and client.get_run(parent).info.status == "RUNNING"
    client.set_tag(parent, TAG_WATCHER, watcher_tag(detached=True))
    reason = settle_detached(cfg, store)
    assert reason is not None and reason.startswith("no Slurm task of sweep t is queued or running and 3 cell(s)")
    assert client.get_run(parent).info.status == "KILLED"
    assert stopped_line(cfg, cfg.name) == f"sweep t: its parent run {parent} ended KILLED: {reason}"
    assert reopen(client, parent) and client.get_run(parent).info.status == "RUNNING"  # a task starts on it again
    assert stopped_line(cfg, cfg.name) is None


def test_status_is_read_only_and_status_repair_ends_an_abandoned_detached_parent(make_config, monkeypatch):
    """Issue 58.4: plain `status` writes nothing to MLflow (the abandoned detached sweep's parent stays RUNNING,
    its tags and end time untouched); `status --repair` ends it as its last worker would have, and says so."""
    from bronchocli.sweep import entry
    from bronchocli.sweep.summary import TAG_LAUNCHER, TAG_STOPPED, TAG_WATCHER, watcher_tag

    cfg = two_stages(make_config)
    walk, store = walk_of(cfg)
    client, parent = _parent(cfg)
    client.set_tag(parent, TAG_LAUNCHER, "slurm")
    client.set_tag(parent, TAG_WATCHER, watcher_tag(detached=True))
    FakeSlurm(monkeypatch, [])  # every task cancelled while it was pending: none ran to end the parent
    before = client.get_run(parent)
    state = entry.status(cfg, cfg.name, console=Console(quiet=True))
    after = client.get_run(parent)
    assert len(state.cells()) == len(walk.cells(walk.stages[0]))  # shown: the first stage's cells
    assert (after.info.status, after.info.end_time, after.data.tags) == ("RUNNING", before.info.end_time,
                                                                        before.data.tags)
    console = Console(record=True, width=300)
    entry.status(cfg, cfg.name, repair=True, console=console)
    ended = client.get_run(parent)
    assert ended.info.status == "KILLED" and ended.data.tags[TAG_STOPPED].startswith("no Slurm task of sweep t")
    assert f"its parent run {parent} ended KILLED" in console.export_text()
