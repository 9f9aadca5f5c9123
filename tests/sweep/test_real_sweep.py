"""A real sweep: `bronchopose sweep --workers 2` trains two tiny cells end to end (~20 s on 2 quiet cores)."""

from __future__ import annotations

from sweep_fakes import runs_by_cell
from tinydata import write_tiny_dataset

from bronchocli.runs.client import client_for
from bronchocli.runs.cores import machine_cores
from bronchocli.runs.records import TAG_CELL_KEY
from bronchocli.sweep import FINISHED, SweepStore


def test_a_real_two_worker_sweep_trains_each_cell_once(cli, make_config, tmp_path):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=4, frames=8, image_size=32)
    cfg = make_config(
        archs=("baseline", "lstm"), sweep={"heartbeat_s": 1.0, "stale_after_s": 30.0},
        splits={"train": 2, "val": 1, "test": 1, "cross_subject_val": 1},
        data={"window": 3, "cache_dir": "cache"},
        train={"batch_size": 3, "steps": 2, "val_every": 2, "bn_recalibrate": 1},
    )
    path = str(cfg.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "-c", path, "--workers", "2")
    assert code == 0, out + err
    rows = SweepStore(cfg.paths.storage_url).rows(cfg.name)
    assert [r.state for r in rows] == [FINISHED, FINISHED]
    assert runs_by_cell(cfg) == {r.cell_key: 1 for r in rows}
    client = client_for(cfg)
    pin = max(1, machine_cores() // 2)
    for row in rows:
        run = client.get_run(row.run_id)
        assert run.data.tags[TAG_CELL_KEY] == row.cell_key and run.data.tags["sweep_claim"] == row.token
        assert "pair.pos_l2.mean" in run.data.metrics and "acc.pos_l2.mean" in run.data.metrics
        assert 1 <= int(run.data.params["threads"]) <= pin  # the CPU is split between the two workers
    code, out, _ = cli("status", "-c", path)
    assert code == 0 and all(r.run_id in out for r in rows)
    assert out.count("finished") == 2
