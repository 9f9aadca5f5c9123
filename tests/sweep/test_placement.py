"""GPU placement of sweep workers, tested without a GPU by faking the device list."""

from __future__ import annotations

import pytest
from rich.console import Console
from sweep_fakes import fake_runner, runs_by_cell

from bronchocli.errors import BronchoError
from bronchocli.sweep import SweepStore
from bronchocli.sweep.launch import Submitted, submit_missing, watch
from bronchocli.sweep.launchers import LocalLauncher
from bronchocli.sweep.placement import assign, default_workers, parse_gpus, visible_gpus
from bronchocli.sweep.plan import prepare_walk

SMI = "\n".join(f"GPU {i}: NVIDIA H100 80GB HBM3 (UUID: GPU-{i:08d})" for i in range(8)) + "\n"


def test_visible_gpus_honour_cuda_visible_devices_then_nvidia_smi():
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": "2,3"}, smi=SMI) == ["2", "3"]
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": ""}, smi=SMI) == []
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": "-1"}, smi=SMI) == []
    assert visible_gpus({}, smi=SMI) == [str(i) for i in range(8)]
    assert visible_gpus({}, smi="") == []


def test_workers_are_spread_round_robin_and_pack_k_per_gpu():
    gpus = [str(i) for i in range(8)]
    assert assign(8, gpus) == gpus  # one worker per GPU: none lands on GPU 0 twice
    assert assign(4, ["0", "1"]) == ["0", "1", "0", "1"]  # K = 2 cells per GPU
    assert assign(3, []) == [None, None, None]
    assert default_workers(["0", "1"], per_gpu=4) == 8 and default_workers([], per_gpu=4) == 1


def test_gpu_flags_are_checked_against_the_machine():
    assert parse_gpus("auto", ["0", "1"]) == ["0", "1"] and parse_gpus("none", ["0"]) == []
    assert parse_gpus("1", ["0", "1"]) == ["1"]
    with pytest.raises(BronchoError, match="--gpus '5': 5 not among this machine's GPUs \\(0, 1\\)"):
        parse_gpus("5", ["0", "1"])


def test_each_worker_process_sees_only_its_gpu(make_config, tmp_path, fake_dir):
    cfg = make_config(archs=("baseline", "lstm", "convlstm", "conv3d"))
    store = SweepStore(cfg.paths.storage_url)
    walk, plan = prepare_walk(cfg, store, dataset=False)
    launcher, console, record = LocalLauncher(cfg, runner=fake_runner, gpus=["3", "5"], workers=2), Console(), Submitted()
    with launcher.Session(launcher) as session:  # as `sweep run` drives it
        submit_missing(walk, launcher, console, record, session=session)
        exit_code = watch(walk, launcher, console, record=record, session=session)
    assert exit_code == 0
    seen = {c.key: (fake_dir / f"gpu-{c.key}").read_text() for c in plan.cells}
    assert set(seen.values()) <= {"3", "5"} and len(runs_by_cell(cfg)) == 4
    workers = {r.worker for r in store.rows(cfg.name)}
    assert all(w.endswith((" gpu3", " gpu5")) for w in workers)
