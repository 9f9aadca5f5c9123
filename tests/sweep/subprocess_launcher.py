"""A third launcher, written against the protocol alone (docs/sweep.md, "Adding a launcher"): ``n`` detached
worker processes on this machine, each ``python -m bronchocli.sweep.task <spec>`` in its own session.

One file; nothing in bronchocli names it. It is found by its registration (the ``register`` call at the end, once
the module is imported), as ``subprocess_launcher:SubprocessLauncher``, or through an entry point of the group
``bronchopose.launchers`` (tests/sweep/test_launchers.py installs one). Its own settings are the section
``sweep.launchers.subprocess`` (``Settings``); its worker side, the job id its workers get in their environment
(``Environment``). Its workers are found again through one small JSON record per worker under the sweep's log
folder, so a later command (``sweep cancel``) sees them too. ``after``: a worker of a later stage waits for the
earlier submissions' processes.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from pydantic import Field

from bronchocli.config import Section
from bronchocli.sweep.launchers import STAGE_ENV, Job, Launcher, WorkerEnvironment, Workers, register

JOB_ENV = "SUBPROCESS_LAUNCHER_JOB"  # the worker's job id, as its launcher knows it

SUBMISSIONS = itertools.count()  # this process's submissions: each job's id is <pid>.<n>


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")  # a zombie has exited


class SubprocessSettings(Section):
    """``sweep.launchers.subprocess``."""

    max_workers: int = Field(8, ge=1, le=64)  # workers started for one stage at most


class SubprocessEnvironment(WorkerEnvironment):
    @classmethod
    def detect(cls) -> bool:
        return JOB_ENV in os.environ  # a process its workers started (`bronchopose train` inside one, too)

    @property
    def job_id(self) -> str | None:
        return os.environ.get(JOB_ENV)

    @property
    def task_index(self) -> int | None:
        job = os.environ.get(JOB_ENV, "")
        return int(job.rpartition("_")[2]) if "_" in job else None


class SubprocessJob(Job):
    def cancel(self) -> None:
        for w in self.workers():
            try:
                os.kill(int(w.id), signal.SIGTERM)
            except ProcessLookupError:
                pass


class SubprocessLauncher(Launcher):
    name = "subprocess"
    Job = SubprocessJob
    Settings = SubprocessSettings
    Environment = SubprocessEnvironment
    children: dict[int, subprocess.Popen] = {}  # started by this process: reaped when they exit

    def capacity(self, runnable: int) -> int:
        return max(0, min(runnable, self.settings(self.cfg).max_workers))

    def folder(self) -> Path:
        return self.logs(self.cfg) / "subprocess"

    def describe(self) -> str:
        return f"as detached processes here, logs {self.logs(self.cfg)}"

    def submit(self, n: int, stage: str, after: Sequence[str] = ()) -> Job:
        folder = self.folder()
        folder.mkdir(parents=True, exist_ok=True)
        job = f"{os.getpid()}.{next(SUBMISSIONS)}"
        waits = [str(w.id) for w in self.active() if w.job in after]
        for i in range(n):
            env = {**os.environ, STAGE_ENV: stage, JOB_ENV: f"{job}_{i}", "PYTHONPATH": os.pathsep.join(sys.path)}
            wait = f"while kill -0 {' '.join(waits)} 2>/dev/null; do sleep 1; done; " if waits else ""
            log = open(self.logs(self.cfg) / f"{job}_{i}.log", "ab")  # noqa: SIM115 - the child holds it
            proc = subprocess.Popen(["sh", "-c", wait + 'exec "$@"', "sh", *self.command], env=env, stdout=log,
                                    stderr=subprocess.STDOUT, start_new_session=True)
            log.close()
            self.children[proc.pid] = proc
            (folder / f"{proc.pid}.json").write_text(json.dumps({"job": job, "stage": stage, "pid": proc.pid}))
        return self.Job(self, job)

    def active(self) -> list[Workers]:
        out = []
        for record in sorted(self.folder().glob("*.json")) if self.folder().is_dir() else []:
            data = json.loads(record.read_text())
            proc = self.children.get(data["pid"])
            if proc.poll() is None if proc is not None else _alive(data["pid"]):
                out.append(Workers(str(data["pid"]), data["job"], "RUNNING", data["stage"]))
            else:
                record.unlink(missing_ok=True)
        return out


register(SubprocessLauncher)

