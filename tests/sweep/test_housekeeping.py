"""Orphan checkpoints (issue 22, item 6): status shows their disk per cell and in all, `sweep gc` removes what no
live cell needs; zombie runs (left RUNNING by a dead process) are repaired by `status --repair` and by the next
run of their cell."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bronchocli.io import fmt_bytes, folder_bytes
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.contract import resume_file
from bronchocli.runs.ownership import mark
from bronchocli.runs.processes import TAG_HOST, TAG_PID, TAG_PSTART, process_tags
from bronchocli.runs.records import cell_tags
from bronchocli.sweep import SweepStore, prepare


@pytest.fixture
def project(make_config):
    cfg = make_config(sweep={"max_retries": 1})
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    return cfg, store, plan


def new_run(cfg, cell, status, ckpt_bytes=1000, **tags):
    client = client_for(cfg)
    run_id = client.create_run(experiment_id(client, cfg),
                               tags=cell_tags(cfg, cell, **tags)).info.run_id
    if status != "RUNNING":
        client.set_terminated(run_id, status)
    if ckpt_bytes:
        path = resume_file(cfg, run_id)
        mark(path.parent, run_id, cell.key)  # as checkpoint.save does with its first checkpoint
        path.write_bytes(b"x" * ckpt_bytes)
    return run_id


def test_status_shows_checkpoint_disk_and_gc_removes_only_what_no_live_cell_needs(cli, project):
    cfg, store, plan = project
    base, lstm = plan.cells
    path = str(cfg.paths.base / "experiments.yaml")
    # a FINISHED run (of a cell outside the plan: a plan cell with a FINISHED run is finished, MLflow is the record)
    finished = new_run(cfg, cfg.cell(arch="baseline", rot_loss="ce", population="personalized"), "FINISHED", 1000)
    # a cell given back by Ctrl-C: its KILLED run is resumed by the next worker
    c = store.claim(cfg.name, [base.key], "w1", max_retries=1, stale_after_s=60)
    released = new_run(cfg, base, "KILLED", 3000, sweep_claim=c.token)
    store.set_run_id(c.token, released)
    store.release(c.token)
    # a cell failed for good (2 attempts, max_retries 1): nothing will resume its run
    for _ in range(2):
        c = store.claim(cfg.name, [lstm.key], "w1", max_retries=1, stale_after_s=60)
        failed = new_run(cfg, lstm, "FAILED", 5000, sweep_claim=c.token)
        store.fail(c.token, "CheckpointWriteError: full", failed)
    taken_over = new_run(cfg, lstm, "KILLED", 7000, sweep_claim="a-lost-claim")
    by_train = new_run(cfg, base, "KILLED", 11000)  # `train --resume` continues it
    (resume_file(cfg, by_train).parent / "last.pt.rejected").write_bytes(b"y" * 13000)
    missing = cfg.paths.checkpoints / "0123456789abcdef"
    mark(missing, missing.name, base.key)
    (missing / "last.pt").write_bytes(b"z" * 17000)

    code, out, err = cli("status", "-c", path)
    assert code == 0, err
    # the released cell's checkpoint (and its marker), on its row
    assert "checkpoint" in out and fmt_bytes(folder_bytes(resume_file(cfg, released).parent)) in out
    # finished, both failed runs, the taken-over one, the missing one, and the rejected file
    sizes = {p.name: folder_bytes(p) for p in cfg.paths.checkpoints.iterdir()}
    spare = sum(v for k, v in sizes.items() if k not in (released, by_train)) + 13000
    assert "7 folder(s)" in out and "needed by no live cell" in out and "sweep gc" in out

    code, out, err = cli("sweep", "gc", "-c", path, "--dry-run")
    assert code == 0, err
    assert sorted(p.name for p in cfg.paths.checkpoints.iterdir()) == sorted(sizes)  # nothing removed
    assert (resume_file(cfg, by_train).parent / "last.pt.rejected").exists()
    assert f"gc --dry-run: would free {fmt_bytes(spare)}" in out and "nothing was removed" in out, out

    code, out, err = cli("sweep", "gc", "-c", path)
    assert code == 0, err
    left = sorted(p.name for p in cfg.paths.checkpoints.iterdir())
    assert left == sorted([released, by_train])
    assert not (resume_file(cfg, by_train).parent / "last.pt.rejected").exists()
    assert resume_file(cfg, by_train).is_file() and resume_file(cfg, released).is_file()
    assert f"gc: freed {fmt_bytes(spare)}" in out and finished in out and "no such MLflow run" in out
    code, out, _ = cli("sweep", "gc", "-c", path)
    assert code == 0 and "gc: freed 0 B in 0 checkpoint folder(s)" in out


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_status_repair_ends_runs_whose_process_died_or_whose_claim_is_gone(cli, project):
    cfg, store, plan = project
    base, lstm = plan.cells
    host = process_tags()[TAG_HOST]
    dead = new_run(cfg, base, "RUNNING", 0, **{TAG_HOST: host, TAG_PID: str(dead_pid()),
                                                TAG_PSTART: "?"})
    alive = new_run(cfg, base, "RUNNING", 0, **process_tags())
    elsewhere = new_run(cfg, base, "RUNNING", 0, **{TAG_HOST: "another-node", TAG_PID: "1"})
    orphan = new_run(cfg, lstm, "RUNNING", 0, sweep_claim="a-lost-claim")
    c = store.claim(cfg.name, [lstm.key], "w1", max_retries=1, stale_after_s=60)
    claimed = new_run(cfg, lstm, "RUNNING", 0, sweep_claim=c.token)
    code, out, err = cli("status", "-c", str(cfg.paths.base / "experiments.yaml"), "--repair")
    assert code == 0, err
    client = client_for(cfg)
    status = {r: client.get_run(r).info.status for r in (dead, alive, elsewhere, orphan, claimed)}
    assert status == {dead: "FAILED", alive: "RUNNING", elsewhere: "RUNNING", orphan: "KILLED", claimed: "RUNNING"}
    assert "ended without closing the run" in client.get_run(dead).data.tags["failure_reason"]
    assert "--repair: 2 run(s)" in out


def test_resuming_a_run_whose_process_is_alive_is_refused_in_one_line(cli, project, tmp_path):
    from tinydata import write_tiny_dataset

    cfg, store, plan = project
    write_tiny_dataset(cfg.paths.dataset, patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    base = cfg.cell(arch="baseline", rot_loss="mse", population="personalized")
    run_id = new_run(cfg, base, "RUNNING", 100, **process_tags())
    code, out, err = cli("train", "-c", str(cfg.paths.base / "experiments.yaml"), "-a", "baseline", "-l", "mse",
                         "-P", "personalized", "--resume", "--run-id", run_id, "-q")
    assert code == 2 and len(err.strip().splitlines()) == 1 and f"process {os.getpid()}" in err, out + err
    assert client_for(cfg).get_run(run_id).info.status == "RUNNING"


def test_gc_removes_only_provable_checkpoints_never_other_folders(cli, make_config):
    """Issue 32: with the checkpoints root holding a user's folder, an artifacts-like folder and foreign files
    (and a checkpoint folder a user put a file into), gc removes only the checkpoints' own files."""
    cfg = make_config()
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    base = plan.cells[0]
    root = cfg.paths.checkpoints
    finished = new_run(cfg, base, "FINISHED", 1000)
    shared = new_run(cfg, base, "FINISHED", 2000)
    (root / shared / "notes.txt").write_text("mine")  # a user's file inside a checkpoint folder
    planted = {root / "thesis" / "chapter1.tex": b"\\chapter{1}", root / "artifacts" / "1" / "model.pkl": b"m" * 99,
               root / "photos" / ".config" / "x": b"x", root / "foreign.bin": b"f" * 10,
               root / ("f" * 32) / "last.pt": b"not a checkpoint",  # named like a run, unprovable
               root / "0123" / "last.pt.rejected": b"r"}
    for path, data in planted.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    (root / "link").symlink_to(root / "thesis")
    code, out, err = cli("sweep", "gc", "-c", str(cfg.paths.base / "experiments.yaml"))
    assert code == 0, err
    assert all(path.read_bytes() == data for path, data in planted.items())
    assert (root / "link").is_symlink() and not (root / finished).exists()
    assert sorted(p.name for p in (root / shared).iterdir()) == ["notes.txt"]  # the run's files went, not the note
    assert "left alone: 8 entries" in out and "thesis" in out, out  # and the folder with notes.txt


def test_a_checkpoint_written_before_markers_is_proven_by_reading_it_back(tmp_path):
    torch = pytest.importorskip("torch")
    from bronchocli.runs.ownership import owned_checkpoint, read_identity, remove_checkpoint

    run_id = "a" * 32
    folder = tmp_path / run_id
    folder.mkdir()
    net = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2))  # an OrderedDict, tensors, ints
    opt = torch.optim.Adam(net.parameters())
    torch.save({"format": 2, "run_id": run_id, "cell_key": "k", "model": net.state_dict(),
                "optimizer": opt.state_dict(), "rng": {"torch": torch.get_rng_state(), "python": (3, (1, 2), None)},
                "history": [{"step": 1, "val_loss": 0.5}]}, folder / "last.pt")
    assert read_identity(folder / "last.pt") == (2, run_id)
    assert owned_checkpoint(folder).proof == "checkpoint read back"
    other = tmp_path / ("b" * 32)  # a checkpoint of another run copied in: not this folder's
    other.mkdir()
    torch.save({"format": 2, "run_id": run_id}, other / "last.pt")
    evil = tmp_path / ("c" * 32)  # a pickle that would run code when loaded: read without resolving any global
    evil.mkdir()
    torch.save({"format": 2, "run_id": evil.name, "x": os.getpid}, evil / "last.pt")
    assert owned_checkpoint(other) is None and remove_checkpoint(other, "test") == 0 and (other / "last.pt").exists()
    assert remove_checkpoint(folder, "test") > 0 and not folder.exists()
    assert owned_checkpoint(evil) is not None  # identity read, os.getpid never resolved
