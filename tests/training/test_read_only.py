"""A checkpoints folder made read-only mid-run is told apart from a full one (issue 50): the line says read-only,
never asks to free space, the run ends FAILED (resumable) and resumes once the folder is writable again."""

from __future__ import annotations

import subprocess

import pytest
from mounts import tmpfs
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli.config import load_config
from bronchocli.errors import WriteFailed
from bronchocli.runs.client import client_for
from bronchocli.training.run import run_cell


def test_a_checkpoints_folder_made_read_only_mid_run_says_so_and_the_run_resumes(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    with tmpfs(tmp_path / "ckpt", "1g") as disk:
        cfg = load_config(write_config(tmp_path, steps=8, val_every=2), overrides=[f"runs.checkpoints={disk}"])
        cell = cfg.cell(arch="baseline", rot_loss="mse", population="personalized")

        def read_only_at_step_4(step, values):
            if step == 4:  # the step-2 checkpoint is on disk; the file system turns read-only before step 4's
                subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)

        try:
            with pytest.raises(WriteFailed) as err:
                run_cell(cfg, cell, progress=False, on_validation=read_only_at_step_4)
        finally:
            subprocess.run(["mount", "-o", "remount,rw", str(disk)], check=True)
        line = str(err.value)
        assert "\n" not in line and "not writable (read-only file system), not full" in line, line
        assert "free" not in line and "MB" not in line  # no space to free: the advice is to make it writable
        run = client_for(cfg).search_runs([client_for(cfg).get_experiment_by_name(cfg.experiment_name).experiment_id])
        (failed,) = run
        assert failed.info.status == "FAILED" and "read-only" in failed.data.tags["failure_reason"]
        assert (disk / failed.info.run_id / "last.pt").is_file()  # the step-2 checkpoint: nothing lost
        resumed = run_cell(cfg, cell, progress=False, resume=True)  # writable again: the same run continues
        assert resumed.status == "FINISHED" and resumed.run_id == failed.info.run_id
