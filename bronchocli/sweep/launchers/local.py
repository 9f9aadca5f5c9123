"""The local launcher: a sweep's workers as child processes of the command, pinned round-robin to this machine's
GPUs (``placement``), each logging to its own file under ``sweep.logs``.

Workers are ``multiprocessing`` processes started with ``spawn`` (a fresh
interpreter: no forked CUDA/MLflow/SQLAlchemy state, same behaviour on Linux
and macOS), each running the one worker entry (``stagework.worker_main``) with
its ``WorkerJob``. They sit in their own process group, so a terminal's Ctrl-C
reaches the command alone; ``stop`` sets the shared stop event and sends every
worker one SIGTERM (a second ``stop`` sends SIGINT: abort without waiting for a
checkpoint). A tuning study's workers are the same processes given a
``StudyTask`` (``study``): they claim the study's trial rows.

A tuning study's only worker on a machine without a GPU runs in this process instead (``InProcess``: no
interpreter to start, the trials' progress on this terminal): the launcher's choice, made when it is built;
the driver drives it as any other, its submission returning once the worker is done.

Its ``Session`` (``LocalSession``, a ``session.AttachedSession``) says the
workers are the command's own children: the driver (``sweep.launch``) drives it
as any launcher, inside the session's block (Ctrl-C stops the workers), one
stage at a time (a worker started now would not wait for an earlier stage's),
never replacing a worker that ended with cells left (it waits for cells held
elsewhere, so it ended for a reason another would meet too: an error, a full
disk).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import socket
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from multiprocessing.connection import wait as wait_any
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ... import interrupts
from ...cells import Selection
from ...config import Config
from ..placement import assign, default_workers, parse_gpus, share_counts, visible_gpus
from ..session import EXIT_INTERRUPTED, AttachedSession
from .base import GENERIC, Job, Launcher, Workers

if TYPE_CHECKING:  # the worker side loads when workers are started (the registry lists options without it)
    from ..tuning.rows import StudyTask
    from ..worker import Runner


class LocalProcesses:
    """Worker processes of one command: placed on GPUs round-robin, one log file each, stopped together."""

    def __init__(self, log_dir: Path, gpus: Sequence[str] = (), name: str = "bronchopose-sweep-worker"):
        self.log_dir, self.gpus, self.name = log_dir, list(gpus), name
        self.ctx = mp.get_context("spawn")
        self.event = self.ctx.Event()  # set by ``stop``: workers start nothing new
        self.procs: list[tuple[mp.Process, str, str]] = []  # (process, submission, stage)
        self.log_paths: dict[str, list[Path]] = {}  # submission -> its workers' log files
        self.stops = 0

    def start(self, n: int, target: Callable[..., Any], job: Callable[[str | None, int, str], Any],
              stage: str = "") -> str:
        """Start ``n`` processes running ``target(job(gpu, share, log_path), stop_event)``; the submission's id."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        sub = f"{os.getpid()}-{len({s for _, s, _ in self.procs})}"
        placed = assign(n, self.gpus)
        for gpu, share in zip(placed, share_counts(placed)):
            log_path = self.log_dir / f"{socket.gethostname()}-{os.getpid()}-w{len(self.procs)}.log"
            self.log_paths.setdefault(sub, []).append(log_path)
            proc = self.ctx.Process(target=target, args=(job(gpu, share, str(log_path)), self.event), name=self.name)
            proc.start()
            self.procs.append((proc, sub, stage))
        return sub

    def alive(self) -> list[tuple[mp.Process, str, str]]:
        return [(p, sub, stage) for p, sub, stage in self.procs if p.is_alive()]

    def sentinels(self) -> list[int]:
        return [p.sentinel for p, _, _ in self.alive()]

    def stop(self, submission: str | None = None) -> None:
        """Tell every worker to stop: the first time SIGTERM (release the cell at a checkpoint), then SIGINT.
        ``submission``: only that submission's workers (SIGTERM; the others go on)."""
        if submission is None:
            self.stops += 1
            self.event.set()
        forward = signal.SIGTERM if self.stops <= 1 else signal.SIGINT
        for p, sub, _ in self.alive():
            if p.pid and submission in (None, sub):
                try:
                    os.kill(p.pid, forward)
                except ProcessLookupError:
                    pass

    def join(self) -> list[int | None]:
        """Wait for every worker (again: at once); their exit codes."""
        for p, _, _ in self.procs:
            p.join()
        return [p.exitcode for p, _, _ in self.procs]

    def wait(self, timeout: float | None = None) -> None:
        """Until some worker exits (or ``timeout`` seconds pass)."""
        if sentinels := self.sentinels():
            wait_any(sentinels, timeout=timeout)

    @contextmanager
    def supervised(self) -> Iterator[None]:
        """Start and watch the workers inside: this process's Ctrl-C, SIGTERM and SIGHUP (the terminal closed) stop
        them at once (``stop``: once, then SIGINT), so they give their cells back instead of leaving them to go
        stale; when this process fails, it stops them before waiting. On the way out the handlers are restored
        and every worker is waited for (``join`` then gives their exit codes)."""

        def on_signal(signum: int, frame: Any) -> None:
            interrupts.note(signum)  # the command's exit code names it (143 for SIGTERM, 129 for SIGHUP)
            self.stop()

        previous = {s: signal.signal(s, on_signal) for s in interrupts.STOP_SIGNALS}
        try:
            yield
        except BaseException:  # the parent is failing: stop the workers (they release their work) before waiting
            if self.stops == 0:
                self.stop()
            raise
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
            self.join()


class _Ended:
    """A worker that ran in this process: done when its submission returned (``LocalProcesses``' process's face)."""

    def __init__(self, code: int):
        self.exitcode, self.pid, self.sentinel = code, os.getpid(), None

    def is_alive(self) -> bool:
        return False

    def join(self) -> None:
        return None


class InProcess(LocalProcesses):
    """A study's one worker run in this process (``LocalProcesses``' members): ``start`` works the study's rows
    (``tuning.worker.work_trials``) and returns when none is left; this process's Ctrl-C reaches the trial itself
    (it completes, the worker starts no other, ``start`` raises RunInterrupted: ``tune`` ends 130)."""

    def __init__(self, log_dir: Path, work: Callable[[], int]):
        super().__init__(log_dir)
        self.work = work

    def start(self, n: int, target: Callable[..., Any], job: Callable[[str | None, int, str], Any],
              stage: str = "") -> str:
        sub = f"{os.getpid()}-{len({s for _, s, _ in self.procs})}"
        self.procs.append((_Ended(self.work()), sub, stage))  # type: ignore[arg-type]
        return sub

    @contextmanager
    def supervised(self) -> Iterator[None]:
        yield  # the worker installs nothing: Ctrl-C raises where the trial runs


class LocalSession(AttachedSession):
    """The command's side of its local workers: the block they live in (``LocalProcesses.supervised``: Ctrl-C,
    SIGTERM and SIGHUP stop them), a wait that ends when one exits, their exit codes, and whether they were
    stopped."""

    title, job_word, task_word = "local", "local job", "worker"
    poll_s = 0.5

    def __init__(self, launcher: LocalLauncher):
        super().__init__(launcher)
        self.processes = launcher.processes
        self._block = None
        self._reported = 0  # workers whose exit codes ``exit_codes`` gave already
        self._codes: list[int | None] = []

    def __enter__(self) -> LocalSession:
        self._block = self.processes.supervised()
        self._block.__enter__()
        return self

    def __exit__(self, *exc: Any) -> Any:
        block, self._block = self._block, None
        return block.__exit__(*exc) if block is not None else None

    def submitted(self, job: str, n: int, stage: str, after: Sequence[str]) -> str:
        if isinstance(self.processes, InProcess):
            return f"stage {stage}: its worker ran in this process"
        return f"stage {stage}: {n} local worker process{'es' if n > 1 else ''} started"

    def wait(self, timeout: float) -> None:
        """Until a worker exits or ``timeout`` seconds pass (none running: the seconds)."""
        if self.processes.sentinels():
            self.processes.wait(timeout)
        else:
            time.sleep(timeout)

    def exit_codes(self) -> list[int | None]:
        ended = [p for p, _, _ in self.processes.procs[self._reported:]]
        if any(p.is_alive() for p in ended):
            return []
        for p in ended:
            p.join()
        self._reported = len(self.processes.procs)
        codes = [p.exitcode for p in ended]
        self._codes += codes
        return codes

    @property
    def stopped(self) -> bool:
        """Ctrl-C (or SIGTERM, SIGHUP) reached this command, or a worker was stopped on its own (exit 130)."""
        return self.processes.stops > 0 or EXIT_INTERRUPTED in self._codes


class LocalJob(Job):
    """A submission's worker processes: stopped with SIGTERM (they release their cells), each with its log file."""

    launcher: LocalLauncher

    def cancel(self) -> None:
        self.launcher.processes.stop(self.id)

    def logs(self) -> list[Path]:
        return [p for p in self.launcher.processes.log_paths.get(self.id, []) if p.exists()]


class LocalLauncher(Launcher):
    """Workers as this command's child processes (``LocalProcesses``), each through ``stagework.worker_main``;
    at most ``workers`` at once, pinned round-robin to ``gpus``. A study's only worker without a GPU: this process
    (``InProcess``)."""

    name = "local"
    Session = LocalSession
    Job = LocalJob
    parameters = dict(GENERIC)  # --workers, --gpus, --per-gpu

    def __init__(self, cfg: Config, command: Any = (), *, only: Selection | None = None, runner: Runner | None = None,
                 study: StudyTask | None = None, workers: int | None = None, gpus: str | Sequence[str] | None = None,
                 per_gpu: int | None = None, storage_url: str | None = None, log_dir: Path | None = None):
        """``gpus``: ``--gpus`` (auto, none or a list such as 0,1; checked against this machine's; default auto), or
        the GPUs themselves; ``workers``: ``--workers`` (default: the GPUs x ``--per-gpu``, else 1); ``study``: a
        tuning study's workers (its trial rows, ``sweep.tuning.worker``). Its workers are spawned with their job:
        ``command`` is never made."""
        from ..stagework import worker_config  # lazy: see the imports
        from ..worker import default_runner

        super().__init__(cfg, command, only=only, runner=runner or default_runner, study=study)
        devices = parse_gpus(gpus or "auto", visible_gpus()) if gpus is None or isinstance(gpus, str) else list(gpus)
        self.workers = max(1, workers or default_workers(devices, per_gpu or 1))
        self.storage_url = storage_url or cfg.paths.storage_url
        self.wcfg = worker_config(cfg)
        if study is not None and self.workers == 1 and not devices:
            self.processes: LocalProcesses = InProcess(log_dir or self.logs(cfg), self._work_study)
        else:
            self.processes = LocalProcesses(log_dir or self.logs(cfg), devices)

    def _work_study(self) -> int:
        """The study's rows worked in this process (``InProcess``): the worker's exit code, 0; stopped (a signal
        while a trial ran): RunInterrupted naming the trial and the signal."""
        from ...runs.contract import RunInterrupted  # lazy: see the imports
        from ..plan import open_store
        from ..tuning.worker import stopped_line, work_trials

        assert self.study is not None
        code, worker = work_trials(self.wcfg, open_store(self.wcfg, self.storage_url), self.study,
                                   progress=self.study.progress, storage_url=self.storage_url)
        if code == EXIT_INTERRUPTED:
            raise RunInterrupted(stopped_line(worker.runner.stopped if worker else None))
        return code

    def describe(self) -> str:
        if isinstance(self.processes, InProcess):
            return "in this process"
        gpus = f" on GPUs {','.join(self.processes.gpus)}" if self.processes.gpus else ""
        n = f"{self.workers} worker" + ("s" if self.workers > 1 else "")
        return f"here{gpus} (at most {n}), logs {self.processes.log_dir}"

    def capacity(self, runnable: int) -> int:
        return max(0, min(runnable, self.workers))

    def submit(self, n: int, stage: str, after: Sequence[str] = ()) -> Job:
        from ..stagework import WorkerJob, local_process  # lazy: see the imports

        def job(gpu: str | None, share: int, log_path: str) -> WorkerJob:
            return WorkerJob(self.wcfg, self.storage_url, self.only, LocalLauncher, self.runner, last_stage=stage or None,
                             exit_when_idle=False, ends_parent=False, log_path=log_path, gpu=gpu, gpu_share=share,
                             parent_pid=os.getpid(), cpu_workers=n, study=self.study)

        return self.Job(self, self.processes.start(n, local_process, job, stage))

    def active(self) -> list[Workers]:
        return [Workers(str(p.pid), sub, "RUNNING", stage) for p, sub, stage in self.processes.alive()]
