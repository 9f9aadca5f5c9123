"""Disk: a dead worker's checkpoint is removed when its cell is taken over; `status` shows the local stores' sizes."""

from __future__ import annotations

import re

from sqlalchemy import update
from sweep_fakes import fake_runner
from tinydata import write_tiny_dataset

from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.contract import checkpoint_dir, resume_file
from bronchocli.runs.ownership import mark
from bronchocli.runs.records import cell_tags
from bronchocli.sweep import FINISHED, TAG_CLAIM, SweepStore, Worker, prepare
from bronchocli.sweep.storage import cells_table


def test_taking_over_a_dead_workers_cell_resumes_its_checkpoint_and_touches_no_other(make_config, fake_dir):
    """A takeover never deletes a resumable checkpoint (issue 30): the cell resumes the dead worker's run."""
    cfg = make_config(archs=("baseline",))
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    (cell,) = plan.cells
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    claim = store.claim(cfg.name, [cell.key], "dead:1", max_retries=1, stale_after_s=60)
    lost = client.create_run(exp, tags=cell_tags(cfg, cell, **{TAG_CLAIM: claim.token})).info.run_id
    store.set_run_id(claim.token, lost)
    mark(resume_file(cfg, lost).parent, lost, cell.key)  # as checkpoint.save does with its first checkpoint
    resume_file(cfg, lost).write_bytes(b"x" * 1000)  # the dead worker's last checkpoint
    other = checkpoint_dir(cfg, "someone-elses-run")
    other.mkdir(parents=True)
    with store.engine.begin() as conn:  # the worker died: its heartbeat is long gone
        conn.execute(update(cells_table).values(heartbeat=cells_table.c.heartbeat - 1000))
    assert Worker(cfg, plan.cells, store, fake_runner).run() == 0
    (row,) = store.rows(cfg.name)
    assert (row.state, row.run_id) == (FINISHED, lost)  # resumed (the fake runner reopens the run it is given)
    assert client.get_run(lost).info.status == "FINISHED"
    assert other.is_dir()  # nobody else's folder is touched


def test_status_shows_the_size_of_the_local_stores_in_one_line(cli, make_config, tmp_path):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    cfg = make_config()
    (cfg.paths.checkpoints / "run1").mkdir(parents=True)
    (cfg.paths.checkpoints / "run1" / "last.pt").write_bytes(b"x" * 2_500_000)
    (cfg.paths.artifacts / "1" / "a").mkdir(parents=True)
    (cfg.paths.artifacts / "1" / "a" / "w.bin").write_bytes(b"x" * 1500)
    code, out, err = cli("status", "-c", str(tmp_path / "experiments.yaml"))
    assert code == 0, err
    lines = [line for line in out.splitlines() if line.startswith("disk:")]
    assert len(lines) == 1
    assert re.search(r"MLflow artifacts 1\.5 KB \(\S*artifacts\)", lines[0])
    assert re.search(r"checkpoints 2\.5 MB \(\S*checkpoints\)", lines[0])
    assert "frame caches none" in lines[0]
