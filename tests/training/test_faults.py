"""Faults: a signal -> KILLED run + checkpoint -> resume finishes it exactly; NaN loss -> FAILED with the reason."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pandas as pd
import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli import tracking
from bronchocli.config import load_config
from bronchocli.errors import DataError
from bronchocli.runlayout import RunInterrupted
from bronchocli.training.run import run_cell

MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
TRAIN = ["train", "--arch", "baseline", "--rot-loss", "ce", "--population", "personalized", "--quiet"]


def test_a_signal_at_a_known_step_kills_the_run_and_resume_continues_it_exactly(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=12, image_size=32)
    cfg = load_config(write_config(tmp_path, steps=8, val_every=2))
    cell = cfg.cell(arch="lstm", rot_loss="ce", population="personalized")

    def interrupt_after_step_4(step, values):
        if step == 4:
            os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C delivers; handled by run_cell's own handler

    with pytest.raises(RunInterrupted, match="SIGINT received at step 5/8"):
        run_cell(cfg, cell, progress=False, on_validation=interrupt_after_step_4)
    client = tracking.client_for(cfg)
    (run,) = tracking.search_runs(client, [tracking.experiment_id(client, cfg)])
    run_id = run.info.run_id
    assert run.info.status == "KILLED" and "SIGINT" in run.data.tags["failure_reason"]
    checkpoint = cfg.paths.checkpoints / run_id / "last.pt"
    assert checkpoint.is_file()

    result = run_cell(cfg, cell, progress=False, resume=True)
    assert result.status == "FINISHED" and result.run_id == run_id
    run = client.get_run(run_id)
    assert "failure_reason" not in run.data.tags  # a resumed, finished run has no failure (and no empty tag)
    assert sorted(m.step for m in client.get_metric_history(run_id, "val_loss")) == [2, 4, 6, 8]  # continued
    assert run.data.metrics["train.steps"] == 8 and run.data.metrics["train.pairs_seen"] == 8 * 6
    assert not checkpoint.exists()
    assert len(tracking.search_runs(client, [run.info.experiment_id])) == 1


def test_ctrl_c_on_the_command_exits_130_with_one_line_and_leaves_a_resumable_run(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=12, image_size=32)
    write_config(tmp_path, steps=100_000, val_every=1)  # cannot finish before the signal lands
    env = {**os.environ, "COLUMNS": "200", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-c", MAIN, *TRAIN], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    ckpts = tmp_path / "runs" / "checkpoints"
    deadline = time.monotonic() + 240
    while not (ckpts.is_dir() and any(ckpts.glob("*/last.pt"))):
        assert proc.poll() is None, proc.stdout.read()
        assert time.monotonic() < deadline, "no checkpoint appeared"
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 130, out
    assert "Traceback" not in out and "SIGINT received at step" in out
    cfg = load_config(tmp_path / "experiments.yaml")
    client = tracking.client_for(cfg)
    (run,) = tracking.search_runs(client, [tracking.experiment_id(client, cfg)])
    assert run.info.status == "KILLED"
    assert (cfg.paths.checkpoints / run.info.run_id / "last.pt").is_file()


def test_resume_without_a_resumable_run_is_a_clear_error(tiny_project, cli):
    code, _, err = cli("train", "-c", str(tiny_project / "experiments.yaml"), "--arch", "baseline",
                       "--rot-loss", "mse", "--population", "personalized", "--seed", "7", "--resume")
    assert code == 2 and "no KILLED/FAILED run" in err and "Traceback" not in err


def test_resume_of_an_unknown_run_id_is_a_clear_error(tiny_project, cli):
    code, _, err = cli("train", "-c", str(tiny_project / "experiments.yaml"), "--arch", "baseline",
                       "--rot-loss", "mse", "--population", "personalized", "--resume", "--run-id", "0123abcd")
    assert code == 2 and "--run-id 0123abcd: no such MLflow run" in err and len(err.strip().splitlines()) == 1


def test_non_finite_loss_fails_the_run_with_its_reason(tmp_path):
    root = write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8,
                              image_size=32)
    for csv in root.glob("p*.csv"):  # finite on disk, but the squared error overflows to inf
        table = pd.read_csv(csv)
        table.loc[table.frame % 2 == 1, "pos_x"] = 1e200
        table.to_csv(csv, index=False)
    cfg = load_config(write_config(tmp_path))
    result = run_cell(cfg, cfg.cell(arch="baseline", rot_loss="mse", population="personalized"), progress=False)
    assert result.status == "FAILED"
    assert "non-finite" in result.failure_reason
    run = tracking.client_for(cfg).get_run(result.run_id)
    assert run.info.status == "FAILED" and "non-finite" in run.data.tags["failure_reason"]
    assert "pair.pos_l2.mean" not in run.data.metrics


def test_a_missing_frame_fails_before_any_run_exists(tmp_path):
    root = write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8,
                              image_size=32)
    victim = next((root / "p00" / "ur").glob("*.png"))
    victim.unlink()
    cfg = load_config(write_config(tmp_path))
    with pytest.raises(DataError, match=victim.name):
        run_cell(cfg, cfg.cell(arch="baseline", rot_loss="mse", population="personalized"), progress=False)
    client = tracking.client_for(cfg)
    assert not tracking.search_runs(client, [tracking.experiment_id(client, cfg)])


def test_train_command_cross_subject_camera_frame(tiny_project, cli):
    code, out, err = cli("train", "-c", str(tiny_project / "experiments.yaml"), "-a", "baseline", "-l", "de",
                         "-P", "cross-subject", "--fold", "p01", "--pose-frame", "camera", "-q")
    assert code == 0, err
    assert "FINISHED" in out and "pair pos L2" in out and "training-mean predictor" in out
    cfg = load_config(tiny_project / "experiments.yaml")
    client = tracking.client_for(cfg)
    runs = tracking.search_runs(client, [tracking.experiment_id(client, cfg)], {"fold": "p01"})
    assert len(runs) == 1 and runs[0].data.tags["pose_frame"] == "camera"
    manifest = pd.read_csv(client.download_artifacts(runs[0].info.run_id, "split_manifest.csv"))
    assert set(manifest[manifest.split == "test"].patient) == {"p01"}
    assert "p01" not in set(manifest[manifest.split != "test"].patient)


@pytest.mark.parametrize("args, message", [
    (["-a", "resnet", "-l", "ce", "-P", "personalized"], "arch 'resnet': must be one of baseline, lstm"),
    (["-a", "lstm", "-l", "ce", "-P", "cross-subject"], "fold: cross-subject needs the held-out patient"),
    (["-a", "lstm", "-l", "ce", "-P", "personalized", "--fold", "p00"], "only cross-subject cells"),
    (["-a", "lstm", "-l", "ce", "-P", "personalized", "--pose-frame", "foo"], "--pose-frame 'foo': must be one of world, camera"),
])
def test_bad_flags_are_one_clear_error(tiny_project, cli, args, message):
    code, _, err = cli("train", "-c", str(tiny_project / "experiments.yaml"), *args)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1
