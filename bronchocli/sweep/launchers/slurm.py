"""The Slurm launcher: a sweep's workers as Slurm job arrays, one worker per array task (docs/cluster.md).

Slurm schedules, allocates GPUs, requeues and signals; the claims table still
decides which cell each worker runs, exactly once. Everything Slurm-specific
lives here, behind the launcher protocol (``base.Launcher``): the up-front
checks (sbatch on PATH, shared filesystems, ``sbatch --test-only``), the batch
script, sbatch/squeue/scancel/scontrol, and the worker side (Slurm's job id,
``SLURM_CPUS_PER_TASK``, SIGUSR1 and ``scontrol requeue``). What to run in
each task is the caller's ``command`` (``task.command``: ``python -m
bronchocli.sweep.task <spec>``, ``exec``-ed by the batch script so that
Slurm's signals reach it); how many tasks each stage needs is the generic
watch's arithmetic (``sweep.launch``).

A sweep's jobs are found again through their name (``bronchopose-<sweep>``) and
comment (``bronchopose:<sweep>:<storage id>:<stage>``), so running the command
again submits only what is missing: tasks for the cells left beyond the
tasks already queued or running, and one array per later stage, held by
``--dependency=afterany`` on the arrays before it.

Signals: ``--signal=B:USR1@<signal_delay_s>`` warns the worker before the time
limit: it checkpoints, releases its cell (the attempt is not counted) and
requeues its own task (``scontrol requeue``). SIGTERM (``scancel``, preemption,
node shutdown) also releases the cell; ``--requeue`` lets Slurm put a preempted
or failed-node task back in the queue. Whoever claims a released cell next
resumes its run from the checkpoint on the shared checkpoint path.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator

from ... import urls
from ...config import Config, Section, output_folder
from ...config.sections import MAX_WORKERS
from ...config.spellings import spelled
from ...errors import BronchoError
from ...io import write_text
from ...retry import retry
from ..session import Session
from .base import STAGE_ENV, Job, Launcher, WorkerEnvironment, Workers

log = logging.getLogger(__name__)

NODE_LOCAL = ("/tmp", "/var/tmp", "/dev/shm", "/run")  # folders no other node sees
ACTIVE = ("PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED", "RESIZING",
          "SUSPENDED", "STOPPED", "SIGNALING")
ENDING = ("COMPLETING",)  # listed by squeue but ending (a cancelled task): covers no cell
RELEASE_AFTER_S = 3.0  # a requeued task is started this long after it entered its BeginTime hold
KEY = "sweep.launchers.slurm"  # the launcher's own config section


class SlurmError(BronchoError):
    """sbatch, squeue or scancel failed, or the config cannot run on Slurm (one line)."""


def job_name(sweep: str) -> str:
    """``bronchopose-<sweep>``; a sweep already named ``bronchopose...`` keeps its name (no doubled prefix)."""
    return sweep if sweep.startswith("bronchopose") else f"bronchopose-{sweep}"


def storage_id(cfg: Config) -> str:
    """Tells sweeps of the same name on different storages apart (the URL's hash, password left out)."""
    return hashlib.sha256(urls.redact(cfg.paths.storage_url).encode()).hexdigest()[:8]


def job_comment(cfg: Config, stage: str) -> str:
    return f"bronchopose:{cfg.name}:{storage_id(cfg)}:{stage}"


# sbatch options the launcher sets itself: ``additional`` may not override them (docs/cluster.md)
SLURM_MANAGED = ("array", "job-name", "comment", "output", "error", "open-mode", "signal", "requeue", "no-requeue",
                 "gres", "gpus-per-task", "cpus-per-task", "mem", "time", "partition", "account", "qos",
                 "dependency", "parsable", "wrap", "export", "chdir")


class SlurmSettings(Section):
    """``sweep.launchers.slurm``, the launcher's own section: every array task is one sweep worker (docs/cluster.md).

    Names follow Hydra's submitit launcher where one exists (timeout_min, cpus_per_task, mem_gb,
    array_parallelism, setup, additional, signal_delay_s)."""

    partition: str | None = None
    account: str | None = None
    qos: str | None = None
    timeout_min: int = Field(60, ge=1, le=365 * 24 * 60)  # --time of every array task
    gpus_per_task: int = Field(1, ge=0, le=64)  # --gres=gpu:N; Slurm sets each task's CUDA_VISIBLE_DEVICES
    cpus_per_task: int = Field(2, ge=1, le=MAX_WORKERS)  # also the worker's torch threads (train.threads unset)
    mem_gb: float | None = Field(None, gt=0, le=65536)  # --mem per task; None: the cluster's DefMemPerCPU
    # array tasks (workers) at most per stage; None: one per cell left
    tasks: int | None = Field(None, ge=1, le=100_000)
    array_parallelism: int = Field(256, ge=1, le=100_000)  # tasks of one array running at once (--array=0-N%K)
    signal_delay_s: int = Field(120, ge=1, le=65535)  # SIGUSR1 this long before the time limit: checkpoint, requeue
    setup: list[str] = []  # shell lines run before the worker (module load, source venv/bin/activate)
    additional: dict[str, str | int | bool] = {}  # more sbatch options, e.g. {constraint: a100, exclusive: true}
    python: str | None = None  # interpreter of the workers; None: the one running bronchopose sweep
    logs: str = "runs/slurm-logs"  # per-task logs, <logs>/<array job>_<task>.log (appended across requeues)
    shared_filesystem: bool = False  # opt-in: SQLite/file stores and node-local paths are seen by every node
    exit_when_idle: bool = True  # a task with nothing it can claim exits instead of holding its GPU
    # after the time-limit warning (SIGUSR1) the task checkpoints, gives its cell back, then `scontrol requeue`s
    # itself (works detached; the watcher starts it after 3 s instead of Slurm's ~2 min hold) or just exits
    # (the watcher, or running the command again, submits a new task)
    on_time_limit: spelled(Literal["requeue", "exit"]) = "requeue"

    @field_validator("partition", "account", "qos")
    @classmethod
    def _slurm_name(cls, v: str | None) -> str | None:
        if v is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._,-]*", v):
            raise ValueError("must be a Slurm name: letters, digits, '.', '_', '-' (',' separates several)")
        return v

    @field_validator("setup")
    @classmethod
    def _setup(cls, v: list[str]) -> list[str]:
        if any("\n" in line for line in v):
            raise ValueError("each entry is one shell line (no newline inside); list several lines instead")
        return v

    @field_validator("additional")
    @classmethod
    def _additional(cls, v: dict[str, Any]) -> dict[str, Any]:
        for key in v:
            name = key.replace("_", "-")
            if not re.fullmatch(r"[a-z][a-z0-9-]*", name):
                raise ValueError(f"{key!r}: must be an sbatch long option name without dashes, e.g. constraint")
            if name in SLURM_MANAGED:
                raise ValueError(f"{key!r}: set by the launcher itself (or by its own key in this section); not "
                                 "allowed here")
        return v


def settings(cfg: Config) -> SlurmSettings:
    """``sweep.launchers.slurm``, validated (ConfigError naming the key)."""
    return cfg.launcher_settings("slurm", SlurmSettings)


def logs_dir(cfg: Config) -> Path:
    """``sweep.launchers.slurm.logs``, resolved like the core config's folders."""
    return output_folder(cfg, settings(cfg).logs, f"{KEY}.logs")


# -- up-front checks ------------------------------------------------------------------------------------


def _local_store(url: str) -> bool:
    """A store only this machine's filesystem holds: SQLite, ``file:`` or a bare path (MLflow's file store)."""
    return url.startswith(("sqlite", "file:")) or "://" not in url


def _node_local(path: Path) -> bool:
    return any(path == Path(p) or Path(p) in path.parents for p in NODE_LOCAL)


def check(cfg: Config) -> None:
    """Everything that would make array tasks fail or disagree, before anything is submitted (one line each)."""
    if shutil.which("sbatch") is None:
        raise SlurmError("--launcher slurm: sbatch not found on PATH; run on a Slurm login node (or install Slurm)")
    if not settings(cfg).shared_filesystem:
        _check_shared(cfg)
    # the cluster's own verdict on partition, account, qos, GPUs, memory, time: nothing is queued
    args = [a for a in sbatch_args(cfg, "check", 1) if a != "--parsable"]
    _run([*args, "--test-only", "--wrap", "true"], f"slurm: the cluster refuses {KEY}")


def _check_shared(cfg: Config) -> None:
    hint = f"or set {KEY}.shared_filesystem: true if every node sees this path (docs/cluster.md)"
    if _local_store(cfg.paths.storage_url):
        raise SlurmError(f"storage.url {urls.redact(cfg.paths.storage_url)}: a SQLite claims table cannot be shared "
                         f"by compute nodes; use postgresql://user:${{PGPASSWORD}}@host/db, {hint}")
    if _local_store(cfg.paths.mlflow_uri):
        raise SlurmError(f"runs.uri {urls.redact(cfg.paths.mlflow_uri)}: a file/SQLite MLflow store cannot be "
                         f"shared by compute nodes; use a PostgreSQL database or an MLflow server, {hint}")
    for key, path in (("dataset.root", cfg.paths.dataset), ("runs.artifacts", cfg.paths.artifacts),
                      ("runs.checkpoints", cfg.paths.checkpoints), (f"{KEY}.logs", logs_dir(cfg)),
                      *interpreter_paths(cfg)):
        if _node_local(path):
            raise SlurmError(f"{key} {path}: a node-local folder; compute nodes need it on shared storage, {hint}")


def interpreter_paths(cfg: Config) -> list[tuple[str, Path]]:
    """The workers' interpreter (``python``, else this one) and its virtual environment, as the shared-path
    check names them: a node-local venv fails every task at its first import."""
    given = settings(cfg).python
    python = Path(given or sys.executable)
    key = f"{KEY}.python" if given else f"the Python running bronchopose ({KEY}.python)"
    out = [(key, python)]
    venv = python.parent.parent
    if (venv / "pyvenv.cfg").is_file():
        out.append((f"{key}'s virtual environment", venv))
    elif not given and sys.prefix != sys.base_prefix:
        out.append((f"{key}'s virtual environment", Path(sys.prefix)))
    return out


# -- squeue / sbatch / scancel ---------------------------------------------------------------------------


def _run(args: Sequence[str], what: str) -> str:
    try:
        out = subprocess.run(list(args), capture_output=True, text=True, timeout=60)
    except FileNotFoundError:
        raise SlurmError(f"{args[0]} not found on PATH: run on a Slurm login node") from None
    except subprocess.TimeoutExpired:
        raise SlurmError(f"{what}: {args[0]} did not answer in 60 s (is slurmctld up?)") from None
    if out.returncode != 0:
        first = (out.stderr.strip() or out.stdout.strip() or f"exit code {out.returncode}").splitlines()[-1]
        raise SlurmError(f"{what}: {args[0]} failed: {first}")
    return out.stdout


def _count(task_id: str) -> int:
    """Tasks in one squeue id: 812_3 -> 1, 812_[4-9%2] -> 6, 812_[1,3-4] -> 3."""
    if "[" not in task_id:
        return 1
    spec = task_id.split("[", 1)[1].rstrip("]").split("%", 1)[0]
    n = 0
    for part in spec.split(","):
        lo, _, hi = part.partition("-")
        n += int(hi) - int(lo) + 1 if hi else 1
    return n


def sweep_tasks(cfg: Config) -> list[Workers]:
    """The sweep's array tasks still queued or running (squeue; pending tasks of one array share a line)."""
    out = _run(["squeue", "-h", "--name", job_name(cfg.name), "-o", "%i|%F|%T|%k|%r"], "listing the sweep's jobs")
    prefix = f"bronchopose:{cfg.name}:{storage_id(cfg)}:"
    tasks = []
    for line in out.splitlines():
        parts = line.strip().split("|")
        if len(parts) != 5 or not parts[3].startswith(prefix) or parts[2] not in ACTIVE:
            continue
        tasks.append(Workers(parts[0], parts[1], parts[2], parts[3][len(prefix):], _count(parts[0]), parts[4],
                             ending=parts[2] in ENDING))
    return tasks


def batch_script(cfg: Config, command: Sequence[str], stage: str | None = None) -> str:
    """The array task's script: cd to where the sweep was submitted, the ``setup`` lines, then ``exec command``;
    with ``stage``, the tasks work the stages up to that one only (``STAGE_ENV``): a later stage has its own
    array, sized to its cells, which would otherwise start to find its cells taken."""
    lines = ["#!/bin/bash", "# bronchopose sweep run --launcher slurm: one array task = one sweep worker",
             f"cd {shlex.quote(str(Path.cwd()))}", *settings(cfg).setup,
             *([f"export {STAGE_ENV}={shlex.quote(stage)}"] if stage else []),
             "# exec: the worker is the batch shell, so --signal=B:USR1 and scancel's SIGTERM reach it",
             "exec " + shlex.join(command)]
    return "\n".join(lines) + "\n"


def sbatch_args(cfg: Config, stage: str, tasks: int, dependency: Sequence[str] = ()) -> list[str]:
    s = settings(cfg)
    args = ["sbatch", "--parsable", f"--job-name={job_name(cfg.name)}", f"--comment={job_comment(cfg, stage)}",
            f"--array=0-{tasks - 1}%{s.array_parallelism}", f"--output={logs_dir(cfg) / '%A_%a.log'}",
            "--open-mode=append", f"--signal=B:USR1@{s.signal_delay_s}", "--requeue", f"--time={s.timeout_min}",
            f"--cpus-per-task={s.cpus_per_task}", "--export=ALL"]
    if s.gpus_per_task:
        args.append(f"--gres=gpu:{s.gpus_per_task}")
    if s.mem_gb is not None:
        args.append(f"--mem={max(1, round(s.mem_gb * 1024))}M")
    for key in ("partition", "account", "qos"):
        if getattr(s, key):
            args.append(f"--{key}={getattr(s, key)}")
    for key, value in s.additional.items():
        name = key.replace("_", "-")
        if value is True:
            args.append(f"--{name}")
        elif value is not False:
            args.append(f"--{name}={value}")
    if dependency:
        args.append("--dependency=afterany:" + ":".join(dependency))
    return args


def submit(cfg: Config, stage: str, tasks: int, command: Sequence[str], dependency: Sequence[str] = ()) -> str:
    """Submit one array of ``tasks`` tasks that each run ``command``; returns its job id."""
    folder = logs_dir(cfg)
    folder.mkdir(parents=True, exist_ok=True)
    script = folder / f"{cfg.name}-{stage}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.sh"
    write_text(script, batch_script(cfg, command, stage))
    out = _run([*sbatch_args(cfg, stage, tasks, dependency), str(script)], f"submitting stage {stage}")
    return out.strip().split(";")[0]


def release_held(tasks: Sequence[Workers], held_since: dict[str, float], settle_s: float = RELEASE_AFTER_S) -> None:
    """Start a requeued task now instead of after Slurm's BeginTime hold (``cred_expire``, ~2 min).

    Not at once: slurmd revokes the killed instance's credential with one-second resolution and refuses a new
    one from the same second; a few seconds are enough."""
    now = time.monotonic()
    held = {t.id for t in tasks if t.state == "PENDING" and t.reason == "BeginTime"}
    for task in set(held_since) - held:
        del held_since[task]
    for task in held:
        if now - held_since.setdefault(task, now) >= settle_s:
            try:
                _run(["scontrol", "update", f"JobId={task}", "StartTime=now"], f"releasing requeued task {task}")
                log.info("requeued Slurm task %s started without waiting for its BeginTime hold", task)
            except SlurmError as exc:
                log.warning("%s", exc)
            held_since[task] = now + 60.0  # not again for a minute


def requeue(task: str, tries: int = 3) -> bool:
    """``scontrol requeue`` this task (slurmctld then kills it and queues it again after ``cred_expire``); a
    refusal is logged (and retried): the cell is already released, so the sweep goes on either way."""
    def once() -> None:
        out = subprocess.run(["scontrol", "requeue", task], capture_output=True, text=True, timeout=60)
        if out.returncode != 0:
            why = (out.stderr.strip() or out.stdout.strip() or f"exit code {out.returncode}").splitlines()[-1]
            raise SlurmError(why)

    try:
        retry(once, transient=lambda e: isinstance(e, (SlurmError, OSError, subprocess.TimeoutExpired)),
              what=f"scontrol requeue {task}", attempts=tries, first_delay_s=2.0, max_delay_s=6.0)
        return True
    except (SlurmError, OSError, subprocess.TimeoutExpired) as exc:
        log.error("Slurm task %s was not requeued (%s); its released cell waits for the next task "
                  "(`bronchopose sweep run --launcher slurm` submits one)", task, exc)
        return False


def slurm_task() -> str | None:
    """This process's Slurm job as ``<array job>_<task>`` (or ``<job>``); None outside Slurm."""
    job = os.environ.get("SLURM_ARRAY_JOB_ID") or os.environ.get("SLURM_JOB_ID")
    task = os.environ.get("SLURM_ARRAY_TASK_ID")
    if not job:
        return None
    return f"{job}_{task}" if task and os.environ.get("SLURM_ARRAY_JOB_ID") else job


class SlurmEnvironment(WorkerEnvironment):
    """Inside an array task: Slurm's job id and task index, ``SLURM_CPUS_PER_TASK``; warned of the time limit with
    SIGUSR1 (``--signal=B:USR1@<signal_delay_s>``), the task checkpoints, releases its cell and requeues itself
    (``on_time_limit: requeue``) or just exits."""

    warning_signal = signal.SIGUSR1
    warning_meaning = "Slurm's time-limit warning"

    @classmethod
    def detect(cls) -> bool:
        return bool(os.environ.get("SLURM_JOB_ID"))

    @property
    def job_id(self) -> str | None:
        return slurm_task()

    @property
    def task_index(self) -> int | None:
        index = os.environ.get("SLURM_ARRAY_TASK_ID", "")
        return int(index) if index.isdigit() else None

    @property
    def threads(self) -> int | None:
        threads = os.environ.get("SLURM_CPUS_PER_TASK", "")
        return int(threads) if threads.isdigit() else None

    @property
    def exits_when_idle(self) -> bool:
        return self.settings.exit_when_idle

    def requeue(self) -> bool:
        return requeue(task) if (task := self.job_id) else False

    def done(self, requested: int | None) -> None:
        if not self.warned(requested) or not (task := self.job_id):
            return
        if self.settings.on_time_limit == "requeue":
            log.info("time limit near: requeueing Slurm task %s", task)
            self.requeue()
        else:
            log.info("time limit near: Slurm task %s exits (%s.on_time_limit: exit); a new task takes the cell",
                     task, KEY)


class SlurmSession(Session):
    """The command's side of a Slurm sweep: its words, and the watch's hooks (a requeued task's hold released; a
    queued later stage made to wait for an earlier one submitted again)."""

    title, job_word, task_word = "Slurm", "Slurm array job", "task"

    def __init__(self, launcher: Launcher):
        super().__init__(launcher)
        self._held: dict[str, float] = {}

    def follow(self, queued: Sequence[str], earlier: Sequence[str]) -> None:
        for job in queued:
            try:
                _run(["scontrol", "update", f"JobId={job}", "Dependency=afterany:" + ":".join(earlier)],
                     f"adding job(s) {', '.join(earlier)} to job {job}'s dependency")
            except SlurmError as exc:  # e.g. the job started meanwhile: nothing left to hold back
                log.warning("%s", exc)

    def tick(self, active: Sequence[Workers]) -> None:
        release_held(active, self._held)


class SlurmJob(Job):
    """A Slurm array job: ``scancel`` stops its tasks (its logs, ``<job>_<task>.log``, are found by the default)."""

    def cancel(self) -> None:
        _run(["scancel", self.id], f"cancelling Slurm job {self.id}")


class SlurmLauncher(Launcher):
    """Workers as Slurm array tasks: ``submit`` is one ``sbatch --array``, ``active`` is ``squeue``, a job's
    ``cancel`` is ``scancel``; a task warned of its time limit (SIGUSR1) requeues itself."""

    name = "slurm"
    Settings = SlurmSettings
    Environment = SlurmEnvironment
    Session = SlurmSession
    Job = SlurmJob

    def __init__(self, cfg: Config, command: Any = (), **work: Any):
        super().__init__(cfg, command, **work)
        self.s: SlurmSettings = settings(cfg)

    def describe(self) -> str:
        return f"on Slurm, logs {logs_dir(self.cfg)}/<job>_<task>.log"

    def check(self) -> None:
        check(self.cfg)

    def submit(self, n: int, stage: str, after: Sequence[str] = ()) -> Job:
        return self.Job(self, submit(self.cfg, stage, n, self.command, after))

    def active(self) -> list[Workers]:
        return sweep_tasks(self.cfg)

    def capacity(self, runnable: int) -> int:
        """Tasks beyond those that run at once (``array_parallelism``, ``tasks``) would only start after the work
        is done, each costing a scheduling round to find nothing."""
        s = self.s
        return max(0, min([runnable, s.array_parallelism, *([s.tasks] if s.tasks else [])]))
