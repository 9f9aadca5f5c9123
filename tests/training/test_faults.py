"""Faults: Ctrl-C -> KILLED run + checkpoint -> --resume finishes it; NaN loss -> FAILED with the reason."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from tinyproject import write_config
from tinydata import write_tiny_dataset

from bronchocli import tracking
from bronchocli.config import load_config, make_cell
from bronchocli.training.run import run_cell

MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
TRAIN = ["train", "--arch", "baseline", "--rot-loss", "ce", "--population", "personalized", "--quiet"]


def bronchopose(args, cwd, **kw) -> subprocess.Popen:
    env = {**os.environ, "COLUMNS": "200", "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-c", MAIN, *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, **kw)


def wait_for(predicate, proc: subprocess.Popen, timeout: float = 180.0):
    """Poll until predicate() is truthy; fail if the process exits first or the deadline passes."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        if proc.poll() is not None:
            pytest.fail(f"training exited early ({proc.returncode}):\n{proc.stdout.read()}")
        time.sleep(0.05)
    proc.kill()
    pytest.fail("timed out waiting for training")


def test_ctrl_c_kills_the_run_keeps_a_checkpoint_and_resume_finishes_it(tmp_path):
    # 76 training pairs = 9 batches per epoch: the signal lands while an epoch is still running
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=20, image_size=32)
    write_config(tmp_path, epochs=4)
    proc = bronchopose(TRAIN, tmp_path)
    ckpts = tmp_path / "runs" / "checkpoints"
    last = wait_for(lambda: next(ckpts.glob("*/last.ckpt"), None) if ckpts.is_dir() else None, proc)
    proc.send_signal(signal.SIGINT)  # what Ctrl-C delivers to the foreground process
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 130, out
    assert "Traceback" not in out and "SIGINT" in out
    run_id = last.parent.name
    cfg = load_config(tmp_path / "experiments.yaml")
    client = tracking.client_for(cfg)
    run = client.get_run(run_id)
    assert run.info.status == "KILLED"
    assert "SIGINT" in run.data.tags["failure_reason"]
    assert last.is_file()
    epochs_before = len(client.get_metric_history(run_id, "val_loss"))
    assert 1 <= epochs_before < 4

    resumed = subprocess.run([sys.executable, "-c", MAIN, *TRAIN, "--resume"], cwd=tmp_path,
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED" and run.data.tags["failure_reason"] == ""
    history = client.get_metric_history(run_id, "val_loss")
    assert sorted({m.step for m in history}) == [0, 1, 2, 3]  # continued, not restarted
    assert run.data.metrics["train.epochs"] == 4
    assert not last.exists()  # optimiser state dropped once finished
    assert len(tracking.search_runs(client, [run.info.experiment_id])) == 1


def test_resume_without_a_resumable_run_is_a_clear_error(tiny_project, cli):
    code, _, err = cli("train", "-c", str(tiny_project / "experiments.yaml"), "--arch", "baseline",
                       "--rot-loss", "mse", "--population", "personalized", "--seed", "7", "--resume")
    assert code == 2 and "no KILLED/FAILED run" in err


def test_non_finite_loss_fails_the_run_with_its_reason(tmp_path):
    root = write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8,
                              image_size=32)
    for csv in root.glob("p*.csv"):  # finite on disk, but the squared error overflows to inf
        table = pd.read_csv(csv)
        table.loc[table.frame % 2 == 1, "pos_x"] = 1e200
        table.to_csv(csv, index=False)
    cfg = load_config(write_config(tmp_path))
    result = run_cell(cfg, make_cell(cfg, "baseline", "mse", "personalized", None, 0, "world"), progress=False)
    assert result.status == "FAILED"
    assert "non-finite training loss" in result.failure_reason
    run = tracking.client_for(cfg).get_run(result.run_id)
    assert run.info.status == "FAILED" and "non-finite" in run.data.tags["failure_reason"]
    assert "pair.pos_l2.mean" not in run.data.metrics


def test_a_missing_frame_fails_before_any_run_exists(tmp_path):
    root = write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8,
                              image_size=32)
    victim = next((root / "p00" / "ur").glob("*.png"))
    victim.unlink()
    cfg = load_config(write_config(tmp_path))
    from bronchocli.errors import DataError

    with pytest.raises(DataError, match=victim.name):
        run_cell(cfg, make_cell(cfg, "baseline", "mse", "personalized", None, 0, "world"), progress=False)
    client = tracking.client_for(cfg)
    assert not tracking.search_runs(client, [tracking.experiment_id(client, cfg)])


def test_train_command_cross_subject_camera_frame(tiny_project, cli):
    code, out, err = cli("train", "-c", str(tiny_project / "experiments.yaml"), "-a", "baseline", "-l", "de",
                         "-P", "cross-subject", "--fold", "p01", "--pose-frame", "camera", "-q")
    assert code == 0, err
    assert "FINISHED" in out and "pair pos L2" in out
    cfg = load_config(tiny_project / "experiments.yaml")
    client = tracking.client_for(cfg)
    runs = tracking.search_runs(client, [tracking.experiment_id(client, cfg)], {"fold": "p01"})
    assert len(runs) == 1 and runs[0].data.tags["pose_frame"] == "camera"
    manifest = pd.read_csv(client.download_artifacts(runs[0].info.run_id, "split_manifest.csv"))
    assert set(manifest[manifest.split == "test"].patient) == {"p01"}
    assert "p01" not in set(manifest[manifest.split != "test"].patient)


@pytest.mark.parametrize("args, message", [
    (["-a", "resnet", "-l", "ce", "-P", "personalized"], "--arch 'resnet': must be one of"),
    (["-a", "lstm", "-l", "ce", "-P", "cross-subject"], "--fold: cross-subject needs"),
    (["-a", "lstm", "-l", "ce", "-P", "personalized", "--fold", "p00"], "only cross-subject"),
])
def test_bad_flags_are_one_clear_error(tiny_project, cli, args, message):
    code, _, err = cli("train", "-c", str(tiny_project / "experiments.yaml"), *args)
    assert code == 2 and message in err
