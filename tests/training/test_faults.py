"""Faults: a signal -> KILLED run + checkpoint -> resume finishes it exactly; NaN loss -> FAILED with the reason."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config
from training.test_checkpoint import plant

from bronchocli import interrupts
from bronchocli.config import load_config
from bronchocli.errors import DataError
from bronchocli.runs import client as client_module
from bronchocli.runs.client import MlflowBusy, client_for, experiment_id, retry_busy
from bronchocli.runs.contract import RunInterrupted
from bronchocli.runs.processes import TAG_PID
from bronchocli.runs.records import cell_tags, search_runs
from bronchocli.sweep.launchers import SlurmLauncher
from bronchocli.training import checkpoint
from bronchocli.training.network import PoseRegressor
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
    client = client_for(cfg)
    (run,) = search_runs(client, [experiment_id(client, cfg)])
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
    assert len(search_runs(client, [run.info.experiment_id])) == 1


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
    client = client_for(cfg)
    (run,) = search_runs(client, [experiment_id(client, cfg)])
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


def test_non_finite_loss_fails_the_run_with_its_reason(tmp_path, monkeypatch):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    # Poses that overflow the loss are refused by the reader now (|position| <= 1e6 voxels): a loss that turns NaN
    # stands for a diverging run.
    loss = PoseRegressor.loss
    monkeypatch.setattr(PoseRegressor, "loss", lambda self, *a, **k: loss(self, *a, **k) * float("nan"))
    cfg = load_config(write_config(tmp_path))
    result = run_cell(cfg, cfg.cell(arch="baseline", rot_loss="mse", population="personalized"), progress=False)
    assert result.status == "FAILED"
    assert "non-finite" in result.failure_reason
    run = client_for(cfg).get_run(result.run_id)
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
    client = client_for(cfg)
    assert not search_runs(client, [experiment_id(client, cfg)])


def test_train_command_cross_subject_camera_frame(tiny_project, cli):
    code, out, err = cli("train", "-c", str(tiny_project / "experiments.yaml"), "-a", "baseline", "-l", "de",
                         "-P", "cross-subject", "--fold", "p01", "--pose-frame", "camera", "-q")
    assert code == 0, err
    assert "FINISHED" in out and "pair pos L2" in out and "training-mean predictor" in out
    cfg = load_config(tiny_project / "experiments.yaml")
    client = client_for(cfg)
    runs = search_runs(client, [experiment_id(client, cfg)], {"fold": "p01"})
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


# -- checkpoints that are not ours, and full disks (issue 22, items 1 and 2) ------------------------------------


def killed_run_of(cfg, cell) -> str:
    """A KILLED run of ``cell`` as an interrupted `train` leaves it (without spending a training run on it)."""
    client = client_for(cfg)
    run = client.create_run(experiment_id(client, cfg), tags=cell_tags(cfg, cell))
    client.set_terminated(run.info.run_id, "KILLED")
    return run.info.run_id


def test_a_planted_checkpoint_is_refused_on_resume_and_its_code_never_runs(tmp_path, cli):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path))
    cell = cfg.cell(arch="baseline", rot_loss="ce", population="personalized")
    run_id = killed_run_of(cfg, cell)
    marker = tmp_path / "pwned"
    planted = cfg.paths.checkpoints / run_id / "last.pt"
    plant(planted, marker, "torch")
    code, out, err = cli("train", "-c", str(tmp_path / "experiments.yaml"), *TRAIN[1:], "--resume")
    assert code == 2, out + err
    assert not marker.exists()  # the payload never ran
    assert len(err.strip().splitlines()) == 1 and str(planted) in err and "Traceback" not in err
    run = client_for(cfg).get_run(run_id)
    assert run.info.status == "FAILED" and run.data.tags["failure_reason"].startswith("BadCheckpoint:")
    assert not planted.exists() and planted.with_name("last.pt.rejected").is_file()  # kept aside, never loaded again


def test_train_on_a_full_disk_is_one_line_and_its_run_ends_failed_not_running(tmp_path, cli, monkeypatch):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path))
    real = checkpoint.shutil.disk_usage
    monkeypatch.setattr(checkpoint.shutil, "disk_usage", lambda p: real(p)._replace(free=10_000_000))
    code, out, err = cli("train", "-c", str(tmp_path / "experiments.yaml"), *TRAIN[1:])
    assert code == 2, out + err
    assert len(err.strip().splitlines()) == 1 and "not enough disk space" in err and str(cfg.paths.checkpoints) in err
    client = client_for(cfg)
    (run,) = search_runs(client, [experiment_id(client, cfg)])
    assert run.info.status == "FAILED" and run.data.tags["failure_reason"].startswith("CheckpointWriteError:")


def test_a_checkpoint_write_failing_mid_run_leaves_no_partial_file(tmp_path, cli, monkeypatch):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path))

    def full(obj, f):
        Path(f).write_bytes(b"PK half a checkpoint")
        raise RuntimeError("[enforce fail at inline_container.cc:672] . PytorchStreamWriter failed writing file")

    monkeypatch.setattr(checkpoint.torch, "save", full)
    code, out, err = cli("train", "-c", str(tmp_path / "experiments.yaml"), *TRAIN[1:])
    assert code == 2 and len(err.strip().splitlines()) == 1 and "could not write the checkpoint" in err, out + err
    assert [p for p in cfg.paths.checkpoints.rglob("*") if p.is_file()] == []
    client = client_for(cfg)
    (run,) = search_runs(client, [experiment_id(client, cfg)])
    assert run.info.status == "FAILED"


def test_train_with_checkpoints_on_a_small_file_system(tmp_path, cli, small_fs):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path))
    code, out, err = cli("train", "-c", str(tmp_path / "experiments.yaml"), *TRAIN[1:],
                         "--set", f"runs.checkpoints={small_fs}")
    assert code == 2 and len(err.strip().splitlines()) == 1 and str(small_fs) in err, out + err
    client = client_for(cfg)
    (run,) = search_runs(client, [experiment_id(client, cfg)])
    assert run.info.status == "FAILED" and "disk space" in run.data.tags["failure_reason"]
    assert list(small_fs.rglob("*.tmp")) == []


def test_a_sweep_worker_refuses_a_planted_checkpoint_and_fails_the_cell_with_the_reason(tmp_path, caplog):
    from bronchocli.sweep import FAILED, SweepStore, Worker

    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path)).with_values({"sweep.max_retries": 0})
    cell = cfg.cell(arch="baseline", rot_loss="ce", population="personalized")
    store = SweepStore(cfg.paths.storage_url)
    store.ensure_schema()
    store.add_cells(cfg.name, [cell])
    claim = store.claim(cfg.name, [cell.key], "interrupted-worker", max_retries=0, stale_after_s=60)
    run_id = killed_run_of(cfg, cell)  # the worker was stopped: its cell given back with its KILLED run
    assert store.set_run_id(claim.token, run_id) and store.release(claim.token)
    marker = tmp_path / "pwned"
    plant(cfg.paths.checkpoints / run_id / "last.pt", marker, "torch")
    assert Worker(cfg, [cell], store).run() == 0
    (row,) = store.rows(cfg.name)
    assert row.state == FAILED and row.failure_reason.startswith("BadCheckpoint: checkpoint ")
    assert str(cfg.paths.checkpoints / run_id / "last.pt") in row.failure_reason
    assert not marker.exists() and "Traceback" not in caplog.text
    assert client_for(cfg).get_run(run_id).info.status == "FAILED"


def test_a_full_disk_under_the_artifacts_is_one_line_and_the_run_ends_failed(tmp_path, cli, monkeypatch):
    import errno

    from bronchocli.training import artifacts

    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path))

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(cfg.paths.artifacts / "x" / "predictions.csv"))

    monkeypatch.setattr(artifacts, "log_outcome", full)
    code, out, err = cli("train", "-c", str(tmp_path / "experiments.yaml"), *TRAIN[1:])
    assert code == 2 and len(err.strip().splitlines()) == 1 and "No space left on device" in err, out + err
    assert "predictions.csv" in err and "Traceback" not in out + err
    client = client_for(cfg)
    (run,) = search_runs(client, [experiment_id(client, cfg)])
    assert run.info.status == "FAILED" and run.data.tags["failure_reason"].startswith("WriteFailed:")
    assert (cfg.paths.checkpoints / run.info.run_id / "last.pt").is_file()  # kept: `train --resume` continues


def test_a_disk_filled_while_the_model_is_uploaded_leaves_no_pending_logged_model_on_the_failed_run(tmp_path, cli,
                                                                                                    monkeypatch):
    """Issue 50: the model's files half copied when the disk filled, and the store too full to mark the model FAILED
    at once (the reserve is released only after): the run ends FAILED in one line, its logged model is FAILED, not
    left PENDING beside it (a resumed run that later FINISHED carried it)."""
    import errno

    from mlflow.tracking import MlflowClient

    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path, model_artifact="fp16"))
    finalize = MlflowClient.finalize_logged_model
    refused = []

    def half_copied(self, model_id, local_dir):
        raise OSError(errno.ENOSPC, "No space left on device", str(cfg.paths.artifacts / model_id / "weights.pt"))

    def full_store_once(self, model_id, status):
        if not refused:  # the first write after the disk filled, before the reserve is released
            refused.append(model_id)
            raise OSError(errno.ENOSPC, "database or disk is full")
        return finalize(self, model_id, status)

    monkeypatch.setattr(MlflowClient, "log_model_artifacts", half_copied)
    monkeypatch.setattr(MlflowClient, "finalize_logged_model", full_store_once)
    code, out, err = cli("train", "-c", str(tmp_path / "experiments.yaml"), *TRAIN[1:])
    assert code == 2 and len(err.strip().splitlines()) == 1 and "No space left on device" in err, out + err
    assert "weights.pt" in err and "Traceback" not in out + err and "database or disk is full" not in err
    client = client_for(cfg)
    (run,) = search_runs(client, [experiment_id(client, cfg)])
    assert run.info.status == "FAILED" and run.data.tags["failure_reason"].startswith("WriteFailed:")
    models = client.search_logged_models([run.info.experiment_id],
                                         filter_string=f"source_run_id = '{run.info.run_id}'")
    assert [m.model_id for m in models] == refused  # the one logged model: its first marking was refused
    assert [str(m.status) for m in models] == ["FAILED"], [m.status for m in models]


class StoreLock:
    """An exclusive lock on the MLflow SQLite store, taken from a training callback (another writer, mid-run)."""

    def __init__(self, db) -> None:
        import sqlite3

        self.db, self.conn = db, None
        self.sqlite3 = sqlite3

    def take(self) -> None:
        self.conn = self.sqlite3.connect(self.db, isolation_level=None, check_same_thread=False)
        self.conn.execute("BEGIN EXCLUSIVE")

    def release(self) -> None:
        if self.conn is not None:
            self.conn.execute("ROLLBACK")
            self.conn.close()
            self.conn = None


def test_a_store_locked_mid_run_is_waited_for_and_the_run_finishes(tmp_path, monkeypatch):
    import threading

    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path)).with_values({"runs.busy_timeout_s": 60})
    lock, waited = StoreLock(cfg.paths.base / "runs" / "mlflow.db"), []
    real_retry, real_log = retry_busy, client_module.log_metrics

    def meet(what: str) -> None:  # the first MLflow call after the lock: release it from a thread, later
        if lock.conn is not None and not waited:
            waited.append(what)
            threading.Timer(0.3, lock.release).start()

    def retry(fn, what, bound, shown):  # every call of the busy-waiting client
        meet(what)
        return real_retry(fn, what, bound, shown)

    def log_metrics(client, run_id, metrics, **kw):  # the metric buffer's calls (no busy wait: kept in memory)
        meet("metrics")
        return real_log(client, run_id, metrics, **kw)

    monkeypatch.setattr(client_module, "retry_busy", retry)
    monkeypatch.setattr(client_module, "log_metrics", log_metrics)

    def locked_after_step_2(step, values):
        if step == 2:
            lock.take()

    cell = cfg.cell(arch="baseline", rot_loss="ce", population="personalized")
    try:
        result = run_cell(cfg, cell, progress=False, on_validation=locked_after_step_2)
    finally:
        lock.release()
    assert result.status == "FINISHED" and waited  # an MLflow call met the lock, waited, and went on
    history = client_for(cfg).get_metric_history(result.run_id, "val_loss")
    assert sorted(m.step for m in history) == [2, 4]


def test_a_store_locked_beyond_the_bound_fails_the_run_in_one_line_and_keeps_its_checkpoint(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path)).with_values({"runs.busy_timeout_s": 0.3})
    lock = StoreLock(cfg.paths.base / "runs" / "mlflow.db")
    cell = cfg.cell(arch="baseline", rot_loss="ce", population="personalized")

    def locked_after_step_2(step, values):
        if step == 2:
            lock.take()

    try:
        with pytest.raises(MlflowBusy) as err:
            run_cell(cfg, cell, progress=False, on_validation=locked_after_step_2)
    finally:
        lock.release()
    assert "\n" not in str(err.value) and "database is locked" in str(err.value)
    client = client_for(cfg)
    (run,) = search_runs(client, [experiment_id(client, cfg)])
    # the store stayed locked, so the run could not be ended: RUNNING, tagged with its (this) process, which
    # `status --repair` or the next run of the cell ends once that process is gone; its checkpoint is kept
    assert run.info.status == "RUNNING" and run.data.tags[TAG_PID] == str(os.getpid())
    assert (cfg.paths.checkpoints / run.info.run_id / "last.pt").is_file()


def test_slurms_time_limit_warning_checkpoints_the_step_it_lands_on_and_the_resume_trains_only_the_rest(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=8, image_size=32)
    cfg = load_config(write_config(tmp_path, steps=8, val_every=4))
    cell = cfg.cell(arch="baseline", rot_loss="mse", population="personalized")

    def usr1_after_step_4(step, values):
        if step == 4:
            os.kill(os.getpid(), signal.SIGUSR1)  # --signal=B:USR1@<s>: between the validations of steps 4 and 8

    # the signal is the launcher's, not training's: a Slurm task's worker declares it (``Launcher.Environment``)
    env = SlurmLauncher.Environment
    assert signal.SIGUSR1 not in interrupts.stop_signals()
    with pytest.raises(RunInterrupted, match="SIGUSR1 received at step 5/8 .Slurm's time-limit warning.; "
                                             "checkpoint of step 5 saved to") as info, \
            interrupts.warned_by(env.warning_signal, env.warning_meaning):
        run_cell(cfg, cell, progress=False, on_validation=usr1_after_step_4, extra_tags={"sweep_worker": "first"})
    assert info.value.signal == signal.SIGUSR1 and signal.SIGUSR1 not in interrupts.stop_signals()
    client = client_for(cfg)
    (run,) = search_runs(client, [experiment_id(client, cfg)])
    run_id = run.info.run_id
    assert run.info.status == "KILLED" and run.data.tags["failure_reason"].startswith("SIGUSR1 received")
    assert checkpoint.load(cfg.paths.checkpoints / run_id / "last.pt")["step"] == 5

    result = run_cell(cfg, cell, progress=False, resume=True, extra_tags={"sweep_worker": "second"})
    assert result.status == "FINISHED" and result.run_id == run_id
    run = client.get_run(run_id)
    assert [(m.step, m.value) for m in client.get_metric_history(run_id, "resumed_from_step")] == [(5, 5.0)]
    assert sorted(m.step for m in client.get_metric_history(run_id, "val_loss")) == [4, 8]  # nothing trained twice
    assert run.data.tags["sweep_worker"] == "second"  # the worker that resumed it, not the first one


def test_a_run_cell_that_lost_its_run_to_another_worker_leaves_the_run_and_checkpoint_alone(tmp_path):
    """A stalled sweep worker woken after the takeover: its run_cell writes neither a checkpoint nor a status
    over the run the new owner now trains (issue 30: it used to mark the new owner's run KILLED)."""
    from bronchocli.runs.contract import RunTakenOver

    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=12, image_size=32)
    cfg = load_config(write_config(tmp_path, steps=8, val_every=2))
    cell = cfg.cell(arch="baseline", rot_loss="ce", population="personalized")
    client = client_for(cfg)
    taken: dict[str, str] = {}

    def owns() -> bool:
        return not taken

    def taken_over_after_step_4(step, values):
        if step == 4:  # the new owner reopened the run (RUNNING, its claim) and wrote its checkpoint
            run_id = search_runs(client, [experiment_id(client, cfg)])[0].info.run_id
            client.set_tag(run_id, "sweep_claim", "the new owner")
            (cfg.paths.checkpoints / run_id / "last.pt").write_bytes(b"the new owner's checkpoint")
            taken["run_id"] = run_id
            os.kill(os.getpid(), signal.SIGTERM)  # what the heartbeat's on_lost sends its own worker

    with pytest.raises(RunTakenOver):
        run_cell(cfg, cell, progress=False, on_validation=taken_over_after_step_4, owns=owns)
    run = client.get_run(taken["run_id"])
    assert run.info.status == "RUNNING" and "failure_reason" not in run.data.tags  # the new owner's, untouched
    assert (cfg.paths.checkpoints / run.info.run_id / "last.pt").read_bytes() == b"the new owner's checkpoint"
