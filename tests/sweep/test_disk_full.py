"""A full disk (issue 37.3): the run ends FAILED in one line naming the folder and the space needed, its checkpoint
kept and no attempt of its cell used; the worker stops; after space is freed the same command resumes it once."""

from __future__ import annotations

import re

import pytest
from mounts import tmpfs
from tinydata import write_tiny_dataset

from bronchocli.errors import WriteFailed
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.contract import RunResult, resume_file
from bronchocli.runs.ownership import mark
from bronchocli.runs.records import TAG_FAILURE, cell_tags
from bronchocli.sweep import FAILED, FINISHED, PENDING, SweepStore, Worker, prepare


def test_a_full_disk_fails_the_cell_without_using_an_attempt_and_the_next_sweep_resumes_it(make_config, tmp_path):
    cfg = make_config(archs=("baseline",), sweep={"max_retries": 0})  # no attempt to spare: a used one is final
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    (cell,) = plan.cells
    calls: list[str | None] = []

    def full_disk(cfg, cell, *, resume=None, extra_tags=None, run_id_callback=None, **_):
        """What run_cell does when the disk fills: the run FAILED with the reason, its checkpoint kept, raised."""
        calls.append(resume)
        client = client_for(cfg)
        run_id = resume or client.create_run(experiment_id(client, cfg), tags=cell_tags(cfg, cell, **extra_tags)
                                             ).info.run_id
        run_id_callback(run_id)
        if resume:
            client.update_run(run_id, "RUNNING")
            client.set_terminated(run_id, "FINISHED")
            return RunResult(run_id, "FINISHED", {"pair.pos_l2.mean": 1.0})
        mark(resume_file(cfg, run_id).parent, run_id, cell.key)
        resume_file(cfg, run_id).write_bytes(b"x" * 1000)
        error = WriteFailed(f"{tmp_path}: disk full (no space left on device; 0 B free); needs about 1.0 KB free")
        client.set_tag(run_id, TAG_FAILURE, f"WriteFailed: {error}")
        client.set_terminated(run_id, "FAILED")
        raise error

    with pytest.raises(WriteFailed, match="disk full"):  # the worker stops: every cell would meet the full disk
        Worker(cfg, plan.cells, store, full_disk).run()
    (row,) = store.rows(cfg.name)
    assert (row.state, row.attempts) == (FAILED, 0) and row.failure_reason.startswith("WriteFailed: ")
    assert resume_file(cfg, row.run_id).is_file()  # kept for the resume
    assert client_for(cfg).get_run(row.run_id).info.status == "FAILED"

    assert Worker(cfg, plan.cells, store, full_disk).run() == 0  # space freed: the same sweep again
    assert calls == [None, row.run_id]  # resumed, once
    (done,) = store.rows(cfg.name)
    assert (done.state, done.run_id) == (FINISHED, row.run_id)


def test_a_sweep_worker_stopped_by_a_full_disk_prints_the_cells_line_only_not_a_crash(cli, make_config, fake_dir,
                                                                                      tmp_path):
    """Issue 50: beside the clear disk-full line, the sweep printed "1 worker(s) crashed (exit codes [2])": the worker
    stopped on purpose after recording the failure on its cell's row; that line is the true one."""
    from sweep_fakes import FAKE

    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    cfg = make_config(archs=("baseline", "lstm"), sweep={"stale_after_s": 30.0}, grid_order=True)  # baseline first
    (fake_dir / "full-baseline").touch()
    code, out, err = cli("sweep", "-c", str(cfg.paths.base / "experiments.yaml"), "--workers", "1", *FAKE)
    assert code == 1 and err.strip() == "" and "Traceback" not in out, out + err
    assert "crashed" not in out and "worker(s)" not in out, out
    line = re.sub(r"\s+", " ", out[out.index("failed "):])
    assert "failed baseline" in line and "WriteFailed:" in line and "disk full" in line, out
    rows = {r.coords["arch"]: r for r in SweepStore(cfg.paths.storage_url).rows(cfg.name)}
    assert (rows["baseline"].state, rows["baseline"].attempts) == (FAILED, 0)  # no attempt spent
    assert rows["lstm"].state == PENDING  # the worker stopped: every other cell would meet the same disk
    logs = "".join(p.read_text() for p in cfg.paths.sweep_logs.rglob("*.log"))
    assert "stopped: baseline" in logs and "failed on a full disk" in logs, logs


def test_gc_keeps_a_disk_full_runs_checkpoint_until_its_cell_is_failed_for_good(make_config, tmp_path):
    from sqlalchemy import update

    from bronchocli.sweep.housekeeping import collect_garbage
    from bronchocli.sweep.storage import cells_table

    cfg = make_config(archs=("baseline",), sweep={"max_retries": 1})
    store = SweepStore(cfg.paths.storage_url)
    (cell,) = prepare(cfg, store, dataset=False).cells
    client = client_for(cfg)
    claim = store.claim(cfg.name, [cell.key], "w", max_retries=1, stale_after_s=60)
    run_id = client.create_run(experiment_id(client, cfg), tags=cell_tags(cfg, cell)).info.run_id
    mark(resume_file(cfg, run_id).parent, run_id, cell.key)
    resume_file(cfg, run_id).write_bytes(b"x" * 1000)
    reason = "WriteFailed: /runs: disk full (no space left on device; 0 B free)"
    client.set_tag(run_id, TAG_FAILURE, reason)
    client.set_terminated(run_id, "FAILED")
    assert store.fail(claim.token, reason, run_id, spent=False)  # as the worker records a full disk
    assert collect_garbage(cfg, store, client) == [] and resume_file(cfg, run_id).is_file()  # kept: resumable
    with store.engine.begin() as conn:  # later attempts failed too: the cell is failed for good
        conn.execute(update(cells_table).values(attempts=5))
    (freed,) = collect_garbage(cfg, store, client)
    assert freed[0].run_id == run_id and freed[1] >= 1000 and not resume_file(cfg, run_id).exists()


@pytest.fixture
def disk(tmp_path):
    """An 800 MB tmpfs (the tiny baseline's checkpoint is ~225 MB; the next one needs twice that free beside it)."""
    with tmpfs(tmp_path / "disk", "800m") as mount:
        yield mount


@pytest.mark.slow  # ~3 min on 2 busy cores: two real trainings of the tiny baseline
def test_a_disk_filled_while_the_model_is_logged_fails_in_one_line_and_resumes_once_space_is_freed(
        cli, make_config, tmp_path, fake_dir, disk):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=4, frames=8, image_size=32)
    cfg = make_config(
        archs=("baseline",), sweep={"heartbeat_s": 1.0, "stale_after_s": 30.0},
        runs={"uri": f"sqlite:///{disk}/mlflow.db", "artifacts": f"{disk}/artifacts",
              "checkpoints": f"{disk}/checkpoints"},
        storage=f"sqlite:///{disk}/sweep.db",
        splits={"train": 2, "val": 1, "test": 1, "cross_subject_val": 1}, data={"window": 3, "cache_dir": "cache"},
        train={"batch_size": 3, "steps": 8, "val_every": 4, "bn_recalibrate": 1, "threads": 1,
               "checkpoint_every_s": 0.1})
    command = ("sweep", "-c", str(cfg.paths.base / "experiments.yaml"), "--runner", "disk_fakes:fill_then_train")
    (fake_dir / "fill").touch()
    code, out, err = cli(*command)
    logs = "\n".join(p.read_text() for p in cfg.paths.sweep_logs.rglob("*.log"))
    assert code == 1, out + err + logs
    assert "Traceback" not in out + err and "[SQL:" not in out + err and err.strip() == "", out + err
    assert "crashed" not in out and "worker(s)" not in out, out  # the worker stopped after the cell's line: no crash
    line = re.sub(r"\s+", "", out[out.index("failed "):])  # the cell's failure (one line, wrapped by the console)
    assert "WriteFailed:" in line and "diskfull(" in line and f"freeonthefilesystemmountedat{disk})" in line and "needsabout" in line, out
    (row,) = SweepStore(cfg.paths.storage_url).rows(cfg.name)
    assert (row.state, row.attempts) == (FAILED, 0)
    client = client_for(cfg)
    assert client.get_run(row.run_id).info.status == "FAILED"  # not RUNNING: the reserve gave the room to end it
    assert resume_file(cfg, row.run_id).is_file()
    exp = client.get_run(row.run_id).info.experiment_id
    models = client.search_logged_models([exp], filter_string=f"source_run_id = '{row.run_id}'")
    assert all(str(m.status) == "FAILED" for m in models), models  # a half-logged model: marked, not PENDING

    (disk / "filler").unlink()  # space freed
    (fake_dir / "fill").unlink()
    code, out, err = cli(*command)
    assert code == 0, out + err + "\n".join(p.read_text() for p in cfg.paths.sweep_logs.rglob("*.log"))
    (done,) = SweepStore(cfg.paths.storage_url).rows(cfg.name)
    assert (done.state, done.run_id) == (FINISHED, row.run_id)  # the same run, resumed
    assert len(client.get_metric_history(row.run_id, "resumed_from_step")) == 1  # once
    assert client.get_run(row.run_id).info.status == "FINISHED" and not resume_file(cfg, row.run_id).exists()
    models = client.search_logged_models([exp], filter_string=f"source_run_id = '{row.run_id}'")
    assert sorted(str(m.status) for m in models) == [*["FAILED"] * (len(models) - 1), "READY"], models


@pytest.mark.slow  # ~3 min on 2 busy cores: a real training of the tiny baseline
def test_stores_on_a_small_disk_still_end_the_run_failed_without_spending_an_attempt(cli, make_config, tmp_path,
                                                                                    fake_dir):
    """Issue 50: the stores on a disk with far less than 256 MB free (once: no room for the reserve, so a full disk
    left the cell run, the sweep's parent run and the claims row RUNNING and the re-run waited for the stale cut-off
    and spent an attempt): the reserve is kept on any disk with room for it, so they all end."""
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=4, frames=8, image_size=32)
    with tmpfs(tmp_path / "stores", "64m") as stores:
        cfg = make_config(
            archs=("baseline",), sweep={"heartbeat_s": 1.0, "stale_after_s": 30.0},
            runs={"uri": f"sqlite:///{stores}/mlflow.db", "artifacts": f"{stores}/artifacts"},
            storage=f"sqlite:///{stores}/sweep.db",
            splits={"train": 2, "val": 1, "test": 1, "cross_subject_val": 1}, data={"window": 3},
            train={"batch_size": 3, "steps": 4, "val_every": 2, "bn_recalibrate": 1, "threads": 1})
        command = ("sweep", "-c", str(cfg.paths.base / "experiments.yaml"), "--runner",
                   "disk_fakes:fill_stores_then_train")
        (fake_dir / "fill").touch()
        code, out, err = cli(*command)
        assert code == 1, out + err
        assert "Traceback" not in out + err and "disk full" in out, out + err
        assert "crashed" not in out and "worker(s)" not in out, out  # the cell's line only: no crash beside it
        last = [line for line in out.splitlines() if line.startswith("done ")][-1]
        assert "running 0" in last, out  # nothing left running at the end
        (row,) = SweepStore(cfg.paths.storage_url).rows(cfg.name)
        assert (row.state, row.attempts) == (FAILED, 0)  # ended, and the attempt not spent
        client = client_for(cfg)
        assert client.get_run(row.run_id).info.status == "FAILED"
        parents = [r for r in client.search_runs([client.get_run(row.run_id).info.experiment_id])
                   if r.data.tags.get("run_kind") == "sweep"]
        assert parents and all(p.info.status != "RUNNING" for p in parents)
        assert resume_file(cfg, row.run_id).is_file()  # resumable: nothing lost
