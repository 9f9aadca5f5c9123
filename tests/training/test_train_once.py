"""`train` exactly once per cell, as a sweep is: two `train` of one cell at once give one FINISHED run (issue 49)."""

from __future__ import annotations

import os
import subprocess
import sys

from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli.config import load_config
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import search_runs
from bronchocli.training.once import cell_turn, lock_path
from bronchocli.training.run import run_cell

MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
TRAIN = ["train", "--arch", "baseline", "--rot-loss", "ce", "--population", "personalized", "--quiet"]
ENV = {**os.environ, "COLUMNS": "250", "PYTHONUNBUFFERED": "1"}


def project(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path))
    return cfg, cfg.cell(arch="baseline", rot_loss="ce", population="personalized")


def runs(cfg, status: str = "FINISHED") -> list:
    client = client_for(cfg)
    return [r for r in search_runs(client, [experiment_id(client, cfg)]) if r.info.status == status]


def test_a_second_train_waits_for_the_first_and_reports_its_run(tmp_path):
    cfg, cell = project(tmp_path)
    said: list[str] = []
    with cell_turn(cfg, cell, said.append):  # the first `train` of the cell is in progress (here, in this process)
        assert str(os.getpid()) in lock_path(cfg, cell).read_text()
        second = subprocess.Popen([sys.executable, "-c", MAIN, *TRAIN], cwd=tmp_path, env=ENV, text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        seen = []
        while not any("waiting for it to end" in line for line in seen):  # it says whom it waits for, then waits
            line = second.stdout.readline()
            assert line or second.poll() is None, "".join(seen)
            seen.append(line)
        assert f"pid {os.getpid()}" in seen[-1] and cell.label in seen[-1]
        first = run_cell(cfg, cell, progress=False)
        assert first.status == "FINISHED"
    out = "".join(seen) + second.communicate(timeout=600)[0]
    assert second.returncode == 0, out
    assert f"already has a FINISHED run {first.run_id}" in out and "Traceback" not in out
    assert [r.info.run_id for r in runs(cfg)] == [first.run_id]  # one FINISHED run for the cell
    assert not said and not lock_path(cfg, cell).exists() and not lock_path(cfg, cell).parent.exists()


def test_two_trains_started_together_give_one_finished_run_and_again_trains_another(tmp_path):
    cfg, cell = project(tmp_path)
    procs = [subprocess.Popen([sys.executable, "-c", MAIN, *TRAIN], cwd=tmp_path, env=ENV, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT) for _ in range(2)]
    outs = [p.communicate(timeout=600)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    (finished,) = runs(cfg)
    assert sum("FINISHED in" in o for o in outs) == 1  # one trained ...
    assert sum(f"already has a FINISHED run {finished.info.run_id}" in o for o in outs) == 1  # ... one reported it
    assert not any("Traceback" in o for o in outs)
    again = subprocess.run([sys.executable, "-c", MAIN, *TRAIN, "--again"], cwd=tmp_path, env=ENV, text=True,
                           capture_output=True, timeout=600)
    assert again.returncode == 0, again.stdout + again.stderr
    assert len(runs(cfg)) == 2  # --again keeps its meaning: another run
