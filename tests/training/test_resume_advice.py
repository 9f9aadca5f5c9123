"""Advice that holds (issue 60, item 4): the resume line `train` prints is the command that resumes the same run,
and the tests run what it prints; a fresh `train` of a cell with a resumable run is refused in one line naming
it; a `--resume` whose settings changed the cell key names the run that exists and the settings that differ."""

from __future__ import annotations

import errno
import os
import re
import shlex
import signal

import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli.config import load_config
from bronchocli.errors import WriteFailed
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.contract import RunInterrupted
from bronchocli.runs.records import cell_tags, search_runs
from bronchocli.training import checkpoint, resumable, run

TRAIN = ["train", "--arch", "baseline", "--rot-loss", "ce", "--population", "personalized", "--quiet"]
ADVICE = re.compile(r"resume it with `([^`]+)`|`([^`]+)` resumes it")


@pytest.fixture
def project(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    return load_config(write_config(tmp_path, steps=8, val_every=2))


def printed_command(err: str) -> list[str]:
    """The command a one-line error tells the user to run, as argv for the CLI (without `bronchopose`)."""
    found = ADVICE.findall(" ".join(err.split()))
    assert len(found) == 1, err
    argv = shlex.split("".join(found[0]))
    assert argv[:2] == ["bronchopose", "train"] and "--resume" in argv, argv
    return argv[1:]


def the_run(cfg):
    client = client_for(cfg)
    (only,) = search_runs(client, [experiment_id(client, cfg)])  # never a second run of the cell
    return client, only


def assert_resumed_not_restarted(cfg, run_id: str, step: int, validated: list[int] = [2, 4, 6, 8]) -> None:
    client, only = the_run(cfg)
    assert only.info.run_id == run_id and only.info.status == "FINISHED"
    assert [(m.step, m.value) for m in client.get_metric_history(run_id, "resumed_from_step")] == [(step, step)]
    assert sorted(m.step for m in client.get_metric_history(run_id, "val_loss")) == validated
    assert only.data.metrics["train.steps"] == 8


def test_sigterm_line_is_the_command_that_resumes_the_run_and_running_it_does(project, cli, monkeypatch):
    cfg = project
    config = str(cfg.paths.base / "experiments.yaml")
    real_step = run._StepBar.step

    def term_at_step_3(self, step, total):
        real_step(self, step, total)
        if step == 3:
            os.kill(os.getpid(), signal.SIGTERM)  # a `kill`, scancel or shutdown, between two optimiser steps

    monkeypatch.setattr(run._StepBar, "step", term_at_step_3)
    code, out, err = cli(*TRAIN, "-c", config, "--set", "model.dropout=0.2")
    monkeypatch.setattr(run._StepBar, "step", real_step)
    assert code == 143 and "SIGTERM received at step 3/8" in err and "Traceback" not in out + err, out + err
    _, killed = the_run(cfg)
    assert killed.info.status == "KILLED"
    argv = printed_command(err)
    assert argv[argv.index("--run-id") + 1] == killed.info.run_id and "model.dropout=0.2" in argv

    # the same command without --resume: refused in one line naming the run and the command that resumes it
    code, out, err = cli(*TRAIN, "-c", config, "--set", "model.dropout=0.2")
    assert code == 2 and len(err.strip().splitlines()) == 1, out + err
    assert f"KILLED run {killed.info.run_id}" in err and "--again" in err
    assert printed_command(err) == argv

    code, out, err = cli(*argv)  # what it printed, run as printed
    assert code == 0, out + err
    assert_resumed_not_restarted(cfg, killed.info.run_id, 3)


def test_a_checkpoint_folder_made_unwritable_mid_run_prints_the_command_that_resumes_it(project, cli, monkeypatch):
    cfg = project
    real_save, saves = checkpoint.torch.save, []

    def second_save_refused(obj, f):
        saves.append(f)
        if len(saves) == 2:  # the checkpoint of step 2 is on disk; the folder was made read-only since
            raise OSError(errno.EACCES, "Permission denied", str(f))
        real_save(obj, f)

    monkeypatch.setattr(checkpoint.torch, "save", second_save_refused)
    code, out, err = cli(*TRAIN, "-c", str(cfg.paths.base / "experiments.yaml"))
    monkeypatch.setattr(checkpoint.torch, "save", real_save)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "not writable" in err, out + err
    assert "run the same command again" not in err  # not true of `train`: it starts a new run without --resume
    _, failed = the_run(cfg)
    assert failed.info.status == "FAILED"
    code, out, err = cli(*printed_command(err))
    assert code == 0, out + err
    # step 4 was validated before its checkpoint failed: the resume from step 2's checkpoint validates it again
    assert_resumed_not_restarted(cfg, failed.info.run_id, 2, [2, 4, 4, 6, 8])


def test_again_trains_a_new_run_beside_a_resumable_one_and_says_which_stays(project, cli, monkeypatch):
    cfg = project
    cell = cfg.cell(arch="baseline", rot_loss="ce", population="personalized")
    client = client_for(cfg)
    stopped = client.create_run(experiment_id(client, cfg), tags=cell_tags(cfg, cell)).info.run_id
    client.set_terminated(stopped, "KILLED")
    (cfg.paths.checkpoints / stopped).mkdir(parents=True)
    (cfg.paths.checkpoints / stopped / "last.pt").write_bytes(b"a checkpoint")  # never loaded here
    code, out, err = cli(*TRAIN, "-c", str(cfg.paths.base / "experiments.yaml"), "--again")
    assert code == 0, out + err
    assert f"note: --again: a new run from step 0; the KILLED run {stopped} keeps its checkpoint" in \
        " ".join(out.split())
    assert client.get_run(stopped).info.status == "KILLED"


def test_resume_after_a_setting_changed_the_cell_key_names_the_run_and_the_settings(project, cli):
    cfg = project
    cell = cfg.cell(arch="baseline", rot_loss="ce", population="personalized")
    client = client_for(cfg)
    old = client.create_run(experiment_id(client, cfg), tags=cell_tags(cfg, cell)).info.run_id
    (cfg.paths.base / "config.yaml").write_text(cfg.to_yaml())
    client.log_artifact(old, str(cfg.paths.base / "config.yaml"))
    client.set_terminated(old, "KILLED")
    code, out, err = cli(*TRAIN, "-c", str(cfg.paths.base / "experiments.yaml"), "--resume",
                         "--set", "train.lr=0.0005")
    line = " ".join(err.split())
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in out + err, out + err
    assert f"its KILLED run {old} (key {cell.key}) was made with other settings: train.lr 0.001 (now 0.0005)" in line
    assert "Downloading" not in out + err


def test_the_api_is_told_the_call_that_resumes_and_a_run_without_checkpoint_the_same_command(project):
    cfg = project
    (cfg.paths.checkpoints / "abc").mkdir(parents=True)
    (cfg.paths.checkpoints / "abc" / "last.pt").write_bytes(b"x")
    stopped = RunInterrupted("SIGINT received at step 3/8; checkpoint of step 3 saved to somewhere")
    stopped.run_id, stopped.signal = "abc", signal.SIGINT
    told = resumable.advised(stopped, cfg)
    assert isinstance(told, RunInterrupted) and told.signal == signal.SIGINT and told.exit_code == 130
    assert str(told).endswith("; resume it with `api.train(..., resume='abc')`")
    with resumable.resumed_by(lambda rid: f"bronchopose train -a x --resume --run-id {rid}"):
        assert str(resumable.advised(stopped, cfg)).endswith("`bronchopose train -a x --resume --run-id abc`")
    full = WriteFailed("/x: disk full; free space there and run the same command again: it resumes the run from "
                       "its checkpoint")
    full.run_id = "none-kept"  # failed before its first checkpoint: a new run is what the same command starts
    assert str(resumable.advised(full, cfg)).endswith("free space there and run the same command again (the run "
                                                      "left no checkpoint: a new run starts from step 0)")


def test_sigusr1_outside_slurm_stops_a_plain_train_like_sigterm_never_a_silent_kill(project, cli, monkeypatch,
                                                                                     request):
    """Issue 60 item 5: SIGUSR1's default action kills the process and leaves its run RUNNING; a plain `train`
    (no launcher sends it) checkpoints, ends the run KILLED and exits 128 + 10, before its run too."""
    from bronchocli.training import entry

    # as in a fresh process: SIGUSR1 at its default (a handler an earlier test left in this worker process would
    # be kept by train, which only replaces the default action)
    previous = signal.signal(signal.SIGUSR1, signal.SIG_DFL)
    request.addfinalizer(lambda: signal.signal(signal.SIGUSR1, previous))

    cfg = project
    config = str(cfg.paths.base / "experiments.yaml")
    real_ensure = entry.ensure_dataset

    def usr1_while_preparing(c):
        os.kill(os.getpid(), signal.SIGUSR1)  # before the run exists

    monkeypatch.setattr(entry, "ensure_dataset", usr1_while_preparing)
    code, out, err = cli(*TRAIN, "-c", config)
    monkeypatch.setattr(entry, "ensure_dataset", real_ensure)
    assert code == 138 and "interrupted by SIGUSR1" in err and "Traceback" not in out + err, out + err
    assert signal.getsignal(signal.SIGUSR1) is signal.SIG_DFL  # put back after the command

    real_step = run._StepBar.step

    def usr1_at_step_3(self, step, total):
        real_step(self, step, total)
        if step == 3:
            os.kill(os.getpid(), signal.SIGUSR1)

    monkeypatch.setattr(run._StepBar, "step", usr1_at_step_3)
    code, out, err = cli(*TRAIN, "-c", config)
    monkeypatch.setattr(run._StepBar, "step", real_step)
    assert code == 138 and "SIGUSR1 received at step 3/8 (sent by no launcher" in " ".join(err.split()), out + err
    _, killed = the_run(cfg)
    assert killed.info.status == "KILLED" and (cfg.paths.checkpoints / killed.info.run_id / "last.pt").is_file()
    assert killed.data.tags["failure_reason"].startswith("SIGUSR1 received at step 3/8")
    assert printed_command(err)[-1] == killed.info.run_id
