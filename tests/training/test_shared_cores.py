"""Two `bronchopose train` started at once share the machine's cores (issue 40): their threads add up to at most
the cores, and each run's params say what it got and why."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli.config import load_config
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.cores import machine_cores
from bronchocli.runs.records import search_runs

MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"


@pytest.mark.skipif(machine_cores() < 2, reason="one core: two processes take one thread each, over the cores")
def test_two_trains_started_at_once_split_the_cores(tmp_path):
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path), "COLUMNS": "200"}  # their own claims folder
    env.pop("BRONCHOPOSE_CPU_WORKERS", None)
    procs, projects = [], []
    for name in ("a", "b"):
        root = tmp_path / name
        write_tiny_dataset(root / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
        write_config(root, steps=4, val_every=2)
        projects.append(root)
    for root in projects:  # started back to back, before either has trained a step
        procs.append(subprocess.Popen(
            [sys.executable, "-c", MAIN, "train", "--arch", "baseline", "--rot-loss", "ce", "--population",
             "personalized", "--quiet", "--set", "train.threads=null"],
            cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    try:
        outs = [p.communicate(timeout=1200)[0] for p in procs]  # a bound for a stuck process, not a timing
    finally:
        for p in procs:
            if p.poll() is None:  # timed out: leave no training process behind
                p.kill()
                p.wait()
    assert [p.returncode for p in procs] == [0, 0], outs
    params = []
    for root in projects:
        cfg = load_config(root / "experiments.yaml")
        client = client_for(cfg)
        (run,) = search_runs(client, [experiment_id(client, cfg)])
        params.append(run.data.params)
        assert "train.threads" not in run.data.params  # no explicit count: the share decided
        assert [m.value for m in client.get_metric_history(run.info.run_id, "threads")]  # re-checked per validation
    threads = [int(p["threads"]) for p in params]
    assert sum(threads) <= machine_cores(), params
    assert all(p["threads.source"].startswith(f"share of {machine_cores()} cores with ") for p in params)
    assert any(p["threads.source"].endswith("with 2 processes") for p in params)  # the later one saw the first
    assert list((tmp_path / "bronchopose" / "cores").iterdir()) == []  # both claims given back

