"""``bronchopose sweep --launcher slurm``: the plan's workers as Slurm job arrays (docs/cluster.md).

Slurm schedules, allocates GPUs, requeues and signals; the claims table still
decides which cell each worker runs, exactly once. This module is the Slurm
driver (sbatch, squeue, scancel, scontrol requeue, the batch script) and the
launcher's watch; what to run in each task is the caller's ``command``
(``task.command``: ``python -m bronchocli.sweep.task <spec>``, ``exec``-ed by
the batch script so that Slurm's signals reach it), and how many tasks each
stage needs is the stage walk's arithmetic (``plan.StageWalk.work_left``).

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
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.live import Live

from .. import urls
from ..cells import Selection
from ..config import Config, Stage
from ..errors import BronchoError
from ..io import atomic_path
from ..retry import retry
from ..runs.client import client_for, experiment_id
from ..runs.parents import set_parent_status, sweep_parent
from . import summary
from .plan import Plan, StageWalk, add_cells, cells_left, claimable_now, prepare_walk, read_plan
from .selection import describe_selection
from .status import live_view, progress, slurm_job, summary_line
from .storage import FINISHED, RUNNING, SweepStore
from .worker import EXIT_INTERRUPTED

log = logging.getLogger(__name__)

NODE_LOCAL = ("/tmp", "/var/tmp", "/dev/shm", "/run")  # folders no other node sees
ACTIVE = ("PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED", "RESIZING",
          "SUSPENDED", "STOPPED", "SIGNALING")
ENDING = ("COMPLETING",)  # listed by squeue but ending (a cancelled task): covers no cell
REFRESH_S = 1.0
RELEASE_AFTER_S = 3.0  # a requeued task is started this long after it entered its BeginTime hold


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


def logs_dir(cfg: Config) -> Path:
    return cfg.paths.slurm_logs


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
    if not cfg.slurm.shared_filesystem:
        _check_shared(cfg)
    # the cluster's own verdict on partition, account, qos, GPUs, memory, time: nothing is queued
    args = [a for a in sbatch_args(cfg, "check", 1) if a != "--parsable"]
    _run([*args, "--test-only", "--wrap", "true"], "slurm: the cluster refuses the slurm section")


def _check_shared(cfg: Config) -> None:
    hint = "or set slurm.shared_filesystem: true if every node sees this path (docs/cluster.md)"
    if _local_store(cfg.paths.storage_url):
        raise SlurmError(f"storage.url {urls.redact(cfg.paths.storage_url)}: a SQLite claims table cannot be shared "
                         f"by compute nodes; use postgresql://user:${{PGPASSWORD}}@host/db, {hint}")
    if _local_store(cfg.paths.mlflow_uri):
        raise SlurmError(f"runs.uri {urls.redact(cfg.paths.mlflow_uri)}: a file/SQLite MLflow store cannot be "
                         f"shared by compute nodes; use a PostgreSQL database or an MLflow server, {hint}")
    for key, path in (("dataset.root", cfg.paths.dataset), ("runs.artifacts", cfg.paths.artifacts),
                      ("runs.checkpoints", cfg.paths.checkpoints), ("slurm.logs", logs_dir(cfg)),
                      *interpreter_paths(cfg)):
        if _node_local(path):
            raise SlurmError(f"{key} {path}: a node-local folder; compute nodes need it on shared storage, {hint}")


def interpreter_paths(cfg: Config) -> list[tuple[str, Path]]:
    """The workers' interpreter (``slurm.python``, else this one) and its virtual environment, as the shared-path
    check names them: a node-local venv fails every task at its first import."""
    python = Path(cfg.slurm.python or sys.executable)
    key = "slurm.python" if cfg.slurm.python else "the Python running bronchopose (slurm.python)"
    out = [(key, python)]
    venv = python.parent.parent
    if (venv / "pyvenv.cfg").is_file():
        out.append((f"{key}'s virtual environment", venv))
    elif not cfg.slurm.python and sys.prefix != sys.base_prefix:
        out.append((f"{key}'s virtual environment", Path(sys.prefix)))
    return out


# -- squeue / sbatch / scancel ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Task:
    id: str  # 812_3, or 812_[4-9] for tasks not started yet
    job: str  # the array job id
    state: str
    stage: str
    count: int  # array tasks this line stands for
    reason: str = ""  # squeue's reason of a pending task (BeginTime: a requeued task's hold)


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


def sweep_tasks(cfg: Config) -> list[Task]:
    """The sweep's array tasks still queued or running (squeue; pending tasks of one array share a line)."""
    out = _run(["squeue", "-h", "--name", job_name(cfg.name), "-o", "%i|%F|%T|%k|%r"], "listing the sweep's jobs")
    prefix = f"bronchopose:{cfg.name}:{storage_id(cfg)}:"
    tasks = []
    for line in out.splitlines():
        parts = line.strip().split("|")
        if len(parts) != 5 or not parts[3].startswith(prefix) or parts[2] not in ACTIVE:
            continue
        tasks.append(Task(parts[0], parts[1], parts[2], parts[3][len(prefix):], _count(parts[0]), parts[4]))
    return tasks


STAGE_ENV = "BRONCHOPOSE_SLURM_STAGE"  # the stage an array was submitted for: its tasks stop after it


def batch_script(cfg: Config, command: Sequence[str], stage: str | None = None) -> str:
    """The array task's script: cd to where the sweep was submitted, the ``setup`` lines, then ``exec command``;
    with ``stage``, the tasks work the stages up to that one only (``STAGE_ENV``): a later stage has its own
    array, sized to its cells, which would otherwise start to find its cells taken."""
    lines = ["#!/bin/bash", "# bronchopose sweep --launcher slurm: one array task = one sweep worker",
             f"cd {shlex.quote(str(Path.cwd()))}", *cfg.slurm.setup,
             *([f"export {STAGE_ENV}={shlex.quote(stage)}"] if stage else []),
             "# exec: the worker is the batch shell, so --signal=B:USR1 and scancel's SIGTERM reach it",
             "exec " + shlex.join(command)]
    return "\n".join(lines) + "\n"


def sbatch_args(cfg: Config, stage: str, tasks: int, dependency: Sequence[str] = ()) -> list[str]:
    s = cfg.slurm
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
    with atomic_path(script) as tmp:
        Path(tmp).write_text(batch_script(cfg, command, stage))
    out = _run([*sbatch_args(cfg, stage, tasks, dependency), str(script)], f"submitting stage {stage}")
    return out.strip().split(";")[0]


def cancel(cfg: Config, console: Console, *, dry_run: bool = False) -> int:
    """``bronchopose sweep --cancel``: scancel every job of this sweep (running workers release their cells);
    ``dry_run``: only list them (squeue, which changes nothing)."""
    jobs = sorted({t.job for t in sweep_tasks(cfg)}, key=int)
    if not jobs:
        console.print(f"no Slurm job of sweep {cfg.name} is queued or running")
        return 0
    if dry_run:
        console.print(f"dry run: would cancel Slurm job(s) {', '.join(jobs)} of sweep {cfg.name}; nothing cancelled")
        return 0
    _run(["scancel", *jobs], "cancelling the sweep's jobs")
    console.print(f"cancelled Slurm job(s) {', '.join(jobs)} of sweep {cfg.name}: running cells are released "
                  "(their runs resume from the checkpoint when the sweep is submitted again)")
    return 0


# -- submitting what is missing --------------------------------------------------------------------------


def tasks_wanted(cfg: Config, runnable: int) -> int:
    """Array tasks worth having for ``runnable`` cells: each task works through cells until none is claimable,
    so tasks beyond those that run at once (``slurm.array_parallelism``, ``slurm.tasks``) would only start after
    the work is done, each costing a scheduling round to find nothing."""
    return max(0, min([runnable, cfg.slurm.array_parallelism, *([cfg.slurm.tasks] if cfg.slurm.tasks else [])]))


def runnable_now(walk: StageWalk, stage: Stage, active: Sequence[Task]) -> int:
    """Cells of ``stage`` tasks can work on now: claimable ones (pending, retryable, a dead worker's once its claim
    is stale) plus those held by a live worker. A cell whose task is gone but whose claim is not stale yet counts
    only once it goes stale: a task submitted earlier would find nothing to claim and exit."""
    cfg = walk.cfg
    plan = read_plan(walk.store, walk.sweep, walk.cells(stage) or [])
    claimable = claimable_now(plan, cfg.sweep.max_retries, walk.store.db_now(), cfg.sweep.stale_after_s)
    live = {t.id for t in active}
    held = sum(1 for c in plan.cells if c.key not in claimable and (r := plan.rows.get(c.key)) is not None
               and r.state == RUNNING and (slurm_job(r.worker) is None or slurm_job(r.worker) in live))
    return len(claimable) + held


def add_dependency(jobs: Sequence[str], earlier: Sequence[str]) -> None:
    """Make queued later-stage arrays wait for every earlier-stage array, a re-submitted one included."""
    for job in jobs:
        try:
            _run(["scontrol", "update", f"JobId={job}", "Dependency=afterany:" + ":".join(earlier)],
                 f"adding job(s) {', '.join(earlier)} to job {job}'s dependency")
        except SlurmError as exc:  # e.g. the job started meanwhile: nothing left to hold back
            log.warning("%s", exc)


def submit_missing(walk: StageWalk, command: Sequence[str], console: Console) -> list[str]:
    """Submit arrays for what the queued/running tasks will not cover; returns the new job ids (none: covered).

    A task works the stages up to the one its array was submitted for (``STAGE_ENV``), never a later one, so
    each stage counts the tasks labelled with it: the first stage with cells left wants a task per cell runnable
    now (``runnable_now``, at most ``tasks_wanted``); a later stage's array waits (``afterany``) for the arrays
    before it, and an array queued for a later stage is made to wait for an earlier stage's new array too
    (``add_dependency``)."""
    cfg = walk.cfg
    # A task being cancelled (scancel: COMPLETING until its processes are gone) claims nothing more: not cover.
    active = [t for t in sweep_tasks(cfg) if t.state not in ENDING]
    for step in walk.steps():  # as the local launcher does: a stage whose source is done is settled first
        if step.settled is not None:
            console.print(describe_selection(step.settled), highlight=False)
            add_cells(cfg, walk.store, walk.cells(step.stage, mine=False) or [])
    submitted: list[str] = []
    earlier: list[str] = []  # array jobs labelled with an earlier stage (queued, running or just submitted)
    first = True
    for stage, left in walk.work_left():
        mine = [t for t in active if t.stage == stage.name]
        if submitted and (queued := sorted({t.job for t in mine if t.state == "PENDING"}, key=int)):
            add_dependency(queued, earlier)
        if left:
            have = sum(t.count for t in mine)
            if first:
                want = tasks_wanted(cfg, runnable_now(walk, stage, active))
                if not want and not have:  # only cells of dead tasks whose claims are not stale yet: wait
                    break
            else:
                want = tasks_wanted(cfg, left)
            if want > have:
                job = submit(cfg, stage.name, want - have, command, () if first else earlier)
                submitted.append(job)
                earlier.append(job)
                console.print(f"submitted Slurm array job {job}: {want - have} task(s) for stage {stage.name}"
                              + ("" if first else f", after job(s) {', '.join(earlier[:-1])}"), highlight=False)
            first = False
        earlier += sorted({t.job for t in mine} - set(earlier), key=int)
    return submitted


def launch(cfg: Config, store: SweepStore, only: Selection, command: Sequence[str], *, detach: bool,
           console: Console, retry_failed: bool = False) -> int:
    """``bronchopose sweep --launcher slurm``: check, prepare the shared state, submit arrays of tasks that each
    run ``command`` for what is missing, and (unless ``detach``) watch the table until the sweep's jobs are gone."""
    check(cfg)  # before touching storage: one line, nothing created, nothing submitted
    store.exists()  # an unreachable storage fails here, in runs.timeout_s, before anything is created
    console.print(f"[bold]sweep[/] {cfg.name} on Slurm  storage {store.redacted}  MLflow "
                  f"{urls.redact(cfg.paths.mlflow_uri)}  logs {logs_dir(cfg)}/<job>_<task>.log")
    walk, _ = prepare_walk(cfg, store, only, retry_failed=retry_failed)
    client = client_for(cfg)
    parent = sweep_parent(client, cfg, experiment_id(client, cfg))  # the cells nest under it
    client.update_run(parent, "RUNNING")  # again RUNNING when the sweep is submitted again
    jobs = submit_missing(walk, command, console)
    if not jobs:
        tasks = sweep_tasks(cfg)
        console.print(f"nothing new to submit: {sum(t.count for t in tasks)} task(s) of this sweep queued or running"
                      if tasks else "nothing left to run")
    summary.record_parent(client, parent, walk)  # the plan on the sweep's parent run; the outcome once watching ends
    if detach:
        console.print("detached: `bronchopose status` shows progress, `bronchopose sweep --cancel` stops the jobs")
        return 0
    code = watch(walk, command, console)
    summary.record_parent(client, parent, walk, finished=True)
    if code != EXIT_INTERRUPTED:  # stopped watching only: the jobs go on, so does the sweep
        set_parent_status(client, parent, code)  # the sweep's parent run ends FINISHED (or FAILED) with it
    return code


def _table_state(plan: Plan, claimable: set[str]) -> tuple:
    """What changes whenever a worker claims, releases, finishes or fails a cell (row versions), or a dead
    worker's claim goes stale (the cells claimable now)."""
    return tuple(sorted((k, r.version) for k, r in plan.rows.items())), tuple(sorted(claimable))


def release_held(tasks: Sequence[Task], held_since: dict[str, float], settle_s: float = RELEASE_AFTER_S) -> None:
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


def watch(walk: StageWalk, command: Sequence[str], console: Console) -> int:
    """The live view of the table while the sweep's jobs run; starts requeued tasks without Slurm's hold
    (``release_held``); tops up tasks when all ended with cells left but progress was made since the last
    submission (a cancelled task's released cell), waiting for a dead task's claim to go stale first (a task
    submitted before would find nothing to claim); Ctrl-C stops watching only."""
    cfg = walk.cfg
    retries, stale_s = cfg.sweep.max_retries, cfg.sweep.stale_after_s
    live = Live(console=console, refresh_per_second=2) if console.is_terminal else None
    last_line, plan, held = "", walk.rows(), {}
    seen_at_submit = _table_state(plan, claimable_now(plan, retries, walk.store.db_now(), stale_s))
    if live is not None:
        live.start()
    try:
        while True:
            try:
                plan, now = walk.rows(), walk.store.db_now()
                tasks = sweep_tasks(cfg)
            except BronchoError as exc:  # a storage or slurmctld hiccup must not end the watch
                log.warning("%s", exc)
                time.sleep(REFRESH_S)
                continue
            n = sum(t.count for t in tasks)
            if live is not None:
                live.update(live_view(plan, retries, max(1, n)))
            elif (line := summary_line(progress(plan, retries, max(1, n), now, stale_s)).plain
                  + f"  tasks {n}") != last_line:
                console.print(line, highlight=False)
                last_line = line
            release_held(tasks, held)
            if not tasks:
                left = cells_left(plan, retries)
                if not left and walk.complete:
                    break
                claimable = claimable_now(plan, retries, now, stale_s)
                if left and not claimable:  # a dead task's cell: claimable once its claim is stale, not before
                    time.sleep(REFRESH_S)
                    continue
                # tasks ended with cells left (a cancelled task gave its cell back, a stage was selected, a dead
                # task's claim went stale): submit again, but only when the table moved since the last submission
                # (tasks that crash at start would otherwise be resubmitted for ever)
                now_seen = _table_state(plan, claimable)
                if now_seen == seen_at_submit or not submit_missing(walk, command, console):
                    console.print(f"[yellow]no Slurm task of sweep {cfg.name} is left and {left} cell(s) are not "
                                  f"done[/]; see the task logs in {logs_dir(cfg)} and run the command again")
                    return 1
                seen_at_submit = now_seen
            time.sleep(REFRESH_S)
    except KeyboardInterrupt:
        console.print("stopped watching: the Slurm jobs go on (`bronchopose sweep --cancel` stops them)")
        return EXIT_INTERRUPTED
    finally:
        if live is not None:
            live.stop()
    console.print(summary_line(progress(plan, retries, 1)))
    return 0 if all(plan.state(c) == FINISHED for c in plan.cells) else 1


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
                  "(`bronchopose sweep --launcher slurm` submits one)", task, exc)
        return False
