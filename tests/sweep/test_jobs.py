"""Issue 58, item 1: a submission is a Job that owns its state, its cancel and its logs (submitit's shape). Cancelling
one job stops its workers only; ``sweep cancel`` stops every job of the sweep and ``--dry-run`` lists each one with
its state and log files; a launcher's ``submit`` that returns anything but a Job is refused in one line."""

from __future__ import annotations

import os

import pytest
from sweep_fakes import FAKE, idle_worker, wait_for
from tinydata import write_tiny_dataset

from bronchocli.sweep.launchers import LocalLauncher
from bronchocli.sweep.launchers.base import job_order


@pytest.fixture
def project(make_config, tmp_path):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    return make_config()


def test_job_ids_sort_in_the_order_they_were_made():
    ids = ["4711.10", "812", "4711.2", "99-1", "99-0", "abc", "1000"]
    assert sorted(ids, key=job_order) == ["99-0", "99-1", "812", "1000", "4711.2", "4711.10", "abc"]


def test_cancelling_one_subprocess_job_stops_its_workers_only(project):
    import subprocess_launcher

    launcher = subprocess_launcher.SubprocessLauncher(project, ["sleep", "300"])
    launcher.logs(project).mkdir(parents=True, exist_ok=True)
    first, second = launcher.submit(2, "grid"), launcher.submit(1, "grid")
    try:
        assert isinstance(first, subprocess_launcher.SubprocessJob) and first != second
        assert launcher.jobs() == [first, second]  # found again from the workers `active` lists
        assert first.state == second.state == "RUNNING" and len(first.workers()) == 2 and len(second.workers()) == 1
        assert [p.name for p in first.logs()] == [f"{first.id}_0.log", f"{first.id}_1.log"]  # its own, not the other's
        assert [p.name for p in second.logs()] == [f"{second.id}_0.log"]

        first.cancel()
        wait_for(lambda: first.state == "DONE", "the first job's workers to stop")
        assert second.state == "RUNNING" and launcher.jobs() == [second]  # the other job goes on

        assert launcher.cancel(dry_run=True) == [second] and second.state == "RUNNING"  # a dry run stops nothing
        assert launcher.cancel() == [second]
        wait_for(lambda: not launcher.active(), "the second job's worker to stop")
        assert launcher.cancel() == []
    finally:
        for w in launcher.active():
            os.kill(int(w.id), 9)


def test_cancelling_one_local_job_stops_its_processes_only(project):
    launcher = LocalLauncher(project, workers=3, gpus="none")
    processes = launcher.processes
    make = lambda gpu, share, log_path: log_path  # noqa: E731 - the idle worker's argument: its log
    first = launcher.Job(launcher, processes.start(2, idle_worker, make, "grid"))
    second = launcher.Job(launcher, processes.start(1, idle_worker, make, "grid"))
    try:
        assert launcher.jobs() == [first, second] and [len(j.workers()) for j in (first, second)] == [2, 1]
        wait_for(lambda: len(first.logs()) == 2 and len(second.logs()) == 1, "the workers' logs")
        assert not set(first.logs()) & set(second.logs())
        first.cancel()
        wait_for(lambda: first.state == "DONE", "the first job's processes to stop")
        assert second.state == "RUNNING" and not processes.event.is_set()  # not a stop of the whole command
        assert launcher.cancel() == [second]
        wait_for(lambda: not launcher.active(), "the second job's process to stop")
    finally:
        for p, _, _ in processes.alive():
            p.kill()
        processes.join()


def test_a_submit_that_returns_no_job_is_one_line_naming_the_launcher(cli, project, fake_dir, monkeypatch):
    import subprocess_launcher

    monkeypatch.setattr(subprocess_launcher.SubprocessLauncher, "submit", lambda self, n, stage, after=(): "4711")
    path = str(project.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "subprocess", *FAKE)
    assert code == 2 and err.strip() == ("error: launcher subprocess: submit returned str '4711', not a Job (return "
                                         'self.Job(self, id): docs/sweep.md, "Adding a launcher")'), err


def test_a_dry_run_cancel_lists_each_job_with_its_state_and_logs(cli, project, monkeypatch):
    import subprocess_launcher

    launcher = subprocess_launcher.SubprocessLauncher(project, ["sleep", "300"])
    launcher.logs(project).mkdir(parents=True, exist_ok=True)
    job = launcher.submit(1, "grid")
    try:
        path = str(project.paths.base / "experiments.yaml")
        code, out, err = cli("sweep", "cancel", "-c", path, "--launcher", "subprocess", "--dry-run")
        assert code == 0 and f"would cancel subprocess job(s) {job.id} of sweep t; nothing cancelled" in out, out + err
        assert f"{job.id}: RUNNING, 1 worker(s), logs {job.logs()[0]}" in out, out
        assert job.state == "RUNNING"
    finally:
        job.cancel()
        wait_for(lambda: job.state == "DONE", "the job's worker to stop")
