"""An example launcher (docs/sweep.md, "Adding a launcher"): a sweep's workers on a list of hosts over SSH.

One module, written against the protocol alone; nothing in bronchocli names it. Install it through an entry point
of the group ``bronchopose.launchers`` in your own package::

    [project.entry-points."bronchopose.launchers"]
    ssh = "ssh_launcher:SshLauncher"

then ``bronchopose sweep run --launcher ssh --ssh-hosts node1,node2`` (``bronchopose sweep run --help`` lists
``--ssh-hosts`` once the entry point is installed; ``api.sweep(..., launcher="ssh", ssh_hosts=["node1", "node2"])``
from Python).

What it declares:

- ``parameters``: its one option, ``ssh_hosts`` (a launcher's own options are named ``<launcher name>_<option>``;
  the generic ``workers``/``gpus``/``per_gpu`` it does not take: each host runs one worker, which claims cells
  until none is left, so the sweep is refused with ``--workers`` in one line naming the launchers that take it);
- the three required methods: ``submit`` (returns the submission as its ``Job``) and ``active`` on the launcher,
  ``cancel`` on its ``Job`` (``SshJob``: a job's logs, ``ssh-<job>_<i>.log``, are found by the default ``logs``);
  and ``describe``, ``check``, ``capacity``;
  each worker runs the command the sweep gives it (``self.command``: ``python -m bronchocli.sweep.task '<spec>'``),
  with ``BRONCHOPOSE_SWEEP_STAGE`` set to its stage, and a worker submitted ``after`` others starts once their
  local processes have exited (so a staged plan's later stage waits for the earlier one, as the default
  ``Session`` expects of a launcher whose workers outlive the command).

A worker on host ``H`` is ``ssh H -- env BRONCHOPOSE_SWEEP_STAGE=<stage> <command>`` (so every host needs the same
project, config file and Python environment at the same path, and storage every host reaches: a PostgreSQL
``storage.url`` and an MLflow server), or the command itself, started here with ``subprocess``, when ``H`` is
``localhost``. Each worker is recorded in a small JSON file under the sweep's log folder (its local process: the
command, or the ``ssh`` client), so a later ``sweep cancel`` finds it; cancelling stops that process (ssh then
closes the session and the remote worker gets SIGHUP: it stops as on Ctrl-C and releases its cell).
"""

from __future__ import annotations

import itertools
import json
import os
import shlex
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bronchocli.errors import BronchoError
from bronchocli.sweep.launchers import STAGE_ENV, Job, Launcher, Parameter, Workers

LOCAL = ("localhost", "127.0.0.1")  # hosts whose workers start here directly, without ssh

SUBMISSIONS = itertools.count()  # this process's submissions: each job's id is <pid>.<n>


def _alive(pid: int) -> bool:
    """The process ``pid`` runs (a zombie has exited)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):
        try:
            os.kill(pid, 0)  # no /proc (macOS): the process exists
        except OSError:
            return False
        return True


class SshJob(Job):
    """One submission: its workers' local processes (the command, or the ``ssh`` client) get SIGTERM."""

    def cancel(self) -> None:
        for w in self.workers():
            try:
                os.kill(int(w.id.rpartition(":")[2]), signal.SIGTERM)
            except ProcessLookupError:
                pass


class SshLauncher(Launcher):
    """One worker per host of ``ssh_hosts`` (a host named twice runs two)."""

    name = "ssh"
    Job = SshJob
    parameters = {
        "ssh_hosts": Parameter(list, "Hosts that run the ssh launcher's workers, one worker each: a comma list "
                               "such as node1,node2 (localhost: a worker started here without ssh).",
                               default=["localhost"]),
    }
    children: dict[int, subprocess.Popen] = {}  # started by this process: reaped when they exit

    def __init__(self, cfg: Any, command: Any = (), *, ssh_hosts: Sequence[str] | None = None, **work: Any):
        """``ssh_hosts``: as given (``--ssh-hosts``), else the parameter's default (``localhost``); ``command``:
        what each worker runs, made at the first submission."""
        super().__init__(cfg, command, **work)
        self.hosts = list(ssh_hosts or self.parameters["ssh_hosts"].default)

    def check(self) -> None:
        if not self.hosts:
            raise BronchoError("--ssh-hosts: no host given; name at least one (e.g. --ssh-hosts localhost)")

    def capacity(self, runnable: int) -> int:
        return max(0, min(runnable, len(self.hosts)))

    def folder(self) -> Path:
        return self.logs(self.cfg) / "ssh"

    def describe(self) -> str:
        return f"on {', '.join(self.hosts)} (ssh; localhost: here), logs {self.logs(self.cfg)}"

    def argv(self, host: str, stage: str, waits: Sequence[int] = ()) -> list[str]:
        """What runs a worker for ``stage`` on ``host``: its command here, or through ``ssh``; started once the
        local processes ``waits`` (the workers of the submissions it comes after) have exited."""
        if host in LOCAL:
            run = list(self.command)
        else:
            run = ["ssh", "-o", "BatchMode=yes", host, "--", shlex.join(["env", f"{STAGE_ENV}={stage}", *self.command])]
        if not waits:
            return run
        pids = " ".join(str(p) for p in waits)
        return ["sh", "-c", f'while kill -0 {pids} 2>/dev/null; do sleep 1; done; exec "$@"', "sh", *run]

    def submit(self, n: int, stage: str, after: Sequence[str] = ()) -> Job:
        folder = self.folder()
        folder.mkdir(parents=True, exist_ok=True)
        job = f"{os.getpid()}.{next(SUBMISSIONS)}"
        env = {**os.environ, STAGE_ENV: stage, "PYTHONPATH": os.pathsep.join(sys.path)}  # this module importable
        waits = [int(w.id.rpartition(":")[2]) for w in self.active() if w.job in after]
        for i in range(n):
            host = self.hosts[i % len(self.hosts)]
            with open(self.logs(self.cfg) / f"ssh-{job}_{i}.log", "ab") as log:
                proc = subprocess.Popen(self.argv(host, stage, waits), env=env, stdout=log, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL, start_new_session=True)
            self.children[proc.pid] = proc
            (folder / f"{proc.pid}.json").write_text(json.dumps({"job": job, "stage": stage, "pid": proc.pid,
                                                                 "host": host}))
        return self.Job(self, job)

    def active(self) -> list[Workers]:
        out = []
        for record in sorted(self.folder().glob("*.json")) if self.folder().is_dir() else []:
            data = json.loads(record.read_text())
            proc = self.children.get(data["pid"])
            if proc.poll() is None if proc is not None else _alive(data["pid"]):
                out.append(Workers(f"{data['host']}:{data['pid']}", data["job"], "RUNNING", data["stage"]))
            else:
                record.unlink(missing_ok=True)
        return out

