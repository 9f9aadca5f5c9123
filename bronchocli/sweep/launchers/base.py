"""The launcher protocol: where a sweep's workers run, and nothing about which cell each runs.

A launcher starts, lists and stops *workers*; the claims table still decides
which cell each worker runs, exactly once (docs/sweep.md, "Launchers"). The
protocol follows submitit's: an executor (``Launcher``) that submits, and a
``Job`` per submission that owns its state, its cancel and its logs, with the
sweep's claims model in place of job results:

- ``submit(n, stage, after)``: start ``n`` workers that work the stages up to
  ``stage`` (the worker entry ``stagework.worker_main``, told the stage in
  ``STAGE_ENV``), started only once the submissions ``after`` have ended;
  returns the submission as a ``Job`` (``self.Job(self, id)``);
- ``active()``: this sweep's workers still queued or running, as ``Workers``
  groups (a submission's id, its stage, how many): what finds a submission again
  in a later command (``jobs()``, ``sweep cancel``);
- ``Job.cancel()``: stop that submission's workers (they release their cells).

Those three (and ``name``) are all a launcher must write: ``submit`` and ``active`` on the launcher, ``cancel`` on
its ``Job`` subclass (``Job = MyJob``). Provided from them: ``jobs()`` (the submissions ``active`` lists, as Jobs),
``cancel(dry_run)`` (every job of this sweep), and on a Job ``workers()``, ``state`` and ``logs()`` (its log files:
the launcher's log folder's files named after the job, unless its Job says otherwise). What else a launcher may
write has a default: ``describe``
(one line: where the workers run and log), ``parameters`` (the options it takes: name -> ``Parameter``, submitit's
executor parameters; ``sweep run --<name-with-dashes>`` on the command line, keywords of ``bronchocli.api``; a
name is ``GENERIC`` or ``<launcher name>_<option>``), ``__init__`` (built by ``sweep run`` and ``tune`` with the
values given for its ``parameters``), ``check`` (refuse what would make workers fail, before anything is
created) and ``capacity`` (workers worth starting for ``runnable`` cells).

What a launcher owns besides: ``Settings``, the model of its own config section ``sweep.launchers.<name>``
(validated by ``settings(cfg)`` when the launcher is looked up; the core config holds it as a plain mapping), in
which two names mean something to the platform: ``logs``, its workers' log folder (``logs(cfg)``; an output root
no other may hold, ``roots(cfg)``), and ``python``, the interpreter its workers run (``python(cfg)``);
``Environment``, the worker side (submitit's JobEnvironment): built inside a worker it started
(``environment(cfg)``), it says the worker's job id and task index, the CPU threads it was given, whether it exits
when idle, the launcher's *warning signal* (Slurm: SIGUSR1 before the time limit; training stops on it and
checkpoints, ``interrupts.warned_by``) and what the worker does after its loop (``done``: Slurm ``requeue``s a task
warned of its time limit); and ``Session``, the submitting command's side (``sweep.session``): whether the workers
outlive the command (the default: a batch system's jobs; the local launcher's are the command's own processes),
what messages call them, and the watch's hooks (Slurm's ``tick`` releases requeued tasks' holds). The driver
(``sweep.launch``) calls the session's methods and never asks what kind of launcher it drives.
"""

from __future__ import annotations

import re
import sys
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, final

from ...config import Config, Section, output_folder
from ...config.arguments import RULES, Rule
from ...errors import BronchoError, ConfigError
from ..session import Session

STAGE_ENV = "BRONCHOPOSE_SWEEP_STAGE"  # the stage a worker was submitted for: it stops after that stage
# Settings names the platform reads in any launcher's section where its ``Settings`` declare them:
SETTING_LOGS = "logs"  # its workers' log folder (an output root, checked with the core config's)
SETTING_PYTHON = "python"  # the interpreter its workers run (None: the one running the command)


@dataclass(frozen=True)
class Parameter:
    """One option a launcher takes, as its ``Launcher.parameters`` declares it: ``--<name-with-dashes>`` on ``sweep
    run`` and ``tune``, ``<name>=`` in ``bronchocli.api``, ``<name>=`` of its ``__init__``. ``type``: int, float, str,
    bool or list (of strings: a comma list on the command line); ``default``: what the launcher does when it is not
    given (said in ``--help``; not giving it passes nothing); ``low``/``high``: a number's inclusive range;
    ``choices``: a string's allowed values; ``short``: a short flag (the generic ``-w``)."""

    type: type = str
    help: str = ""
    default: Any = None
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    short: str | None = None

    def rule(self, name: str) -> Rule:
        """What a value must be, as ``config.arguments`` says it for the API's other arguments."""
        return Rule(flag(name), "strings" if self.type is list else self.type, self.low, self.high)

    def allowed(self, name: str) -> str:
        return f"one of {', '.join(self.choices)}" if self.choices else self.rule(name).allowed()

    def ok(self, name: str, value: Any) -> bool:
        return self.rule(name).ok(value) and (not self.choices or value in self.choices)

    def parse(self, value: Any) -> Any:
        """The command line's value as the API takes it (a list's comma list split; the rest as given)."""
        if self.type is list and isinstance(value, str):
            return [v.strip() for v in value.split(",") if v.strip()]
        return value


def flag(name: str) -> str:
    """A parameter's flag, as the command line spells it: ``per_gpu`` -> ``--per-gpu``."""
    return "--" + name.replace("_", "-")


# The parameters every launcher may take under their plain names (any other is ``<launcher name>_<option>``):
# where the workers run on this machine, as ``sweep run`` always took them (bounds: ``config.arguments.RULES``).
GENERIC: dict[str, Parameter] = {
    "workers": Parameter(int, "Local worker processes (torch threads = cores / N), one per cell left at most. "
                         "Default: GPUs x --per-gpu on a GPU machine, else 1.", low=RULES["workers"].low,
                         high=RULES["workers"].high, short="-w"),
    "gpus": Parameter(str, "GPUs for the local workers, round-robin: auto (every visible one, honouring "
                      "CUDA_VISIBLE_DEVICES; the default), none, or a list such as 0,1.", default="auto"),
    "per_gpu": Parameter(int, "Cells run at once on each GPU (default 1; small cells leave a GPU idle, packing "
                         "several raises throughput).", default=1, low=RULES["per_gpu"].low),
}
NAME = re.compile(r"[a-z][a-z0-9]*(?:_[a-z0-9]+)*")  # a parameter's name: lower case words joined by _


def check_declarations(cls: type[Launcher]) -> None:
    """Refuse, in one line naming the launcher and the parameter, a ``parameters`` entry that is neither a generic
    name declared as ``GENERIC`` has it nor ``<launcher name>_<option>`` with a ``Parameter``; and a launcher whose
    ``Job`` does not say how to cancel a submission."""
    job = getattr(cls, "Job", None)
    if not (isinstance(job, type) and issubclass(job, Job)) or getattr(job, "__abstractmethods__", None):
        raise BronchoError(f"launcher {cls.name}: its Job must be a launchers.Job subclass that writes cancel() "
                           "(class MyJob(Job): def cancel(self): ...; then Job = MyJob in the launcher)")
    params = getattr(cls, "parameters", None)
    if not isinstance(params, Mapping):
        raise BronchoError(f"launcher {cls.name}: parameters must be a mapping of name -> Parameter, not "
                           f"{type(params).__name__}")
    own = cls.name.lower().replace("-", "_") + "_"
    for name, param in params.items():
        where = f"launcher {cls.name}: parameter {name!r}"
        if name in GENERIC:
            if param != GENERIC[name]:
                raise BronchoError(f"{where}: a generic parameter is declared as launchers.GENERIC has it (its "
                                   "type, bounds and meaning are every launcher's)")
        elif not isinstance(name, str) or not name.startswith(own) or not NAME.fullmatch(name) or name == own[:-1]:
            raise BronchoError(f"{where}: must be generic ({', '.join(GENERIC)}) or the launcher's own, "
                               f"{own}<option> (lower case, e.g. {own}hosts)")
        elif not isinstance(param, Parameter) or param.type not in (int, float, str, bool, list):
            raise BronchoError(f"{where}: must be a Parameter of type int, float, str, bool or list")


@dataclass(frozen=True)
class Workers:
    """Workers of this sweep that a launcher started and still sees."""

    id: str  # as the launcher names them (Slurm: 812_3, or 812_[4-9] for tasks not started yet)
    job: str  # the submission they belong to (what ``submit`` returned)
    state: str  # PENDING (not started yet), RUNNING, or the launcher's own word
    stage: str  # the stage they were submitted for
    count: int = 1  # workers this entry stands for
    reason: str = ""  # why a pending one waits (Slurm: BeginTime, a requeued task's hold)
    ending: bool = False  # being stopped (Slurm: COMPLETING after scancel): covers no cell


def job_order(job: str) -> tuple:
    """Submissions in the order they were made where their ids say it (Slurm's ``812``; ``<pid>-<k>``,
    ``<pid>.<k>``), else by name."""
    parts = re.split(r"[-.]", job)
    if all(p.isdigit() for p in parts):
        return (0, *map(int, parts))
    return (1, job)


class Job(ABC):
    """One submission of a launcher (submitit's Job): what ``submit`` returns, and what ``Launcher.jobs`` finds
    again from the workers ``active`` lists, in this command or a later one. It owns its state (``workers``,
    ``state``), its cancel and its logs. A launcher writes ``cancel`` in a subclass (its ``Job``); ``logs`` where
    its log files are not named after the job."""

    def __init__(self, launcher: Launcher, id: str):
        self.launcher, self.id = launcher, str(id)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.launcher.name} {self.id})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Job) and (other.launcher.name, other.id) == (self.launcher.name, self.id)

    def __hash__(self) -> int:
        return hash((self.launcher.name, self.id))

    def workers(self) -> list[Workers]:
        """Its workers still queued or running (the launcher's ``active``, this job's)."""
        return [w for w in self.launcher.active() if w.job == self.id]

    @property
    def state(self) -> str:
        """Its workers' state (``state_of``)."""
        return state_of(self.workers())

    @abstractmethod
    def cancel(self) -> None:
        """Stop its workers (running ones release their cells; queued ones never start)."""

    def logs(self) -> list[Path]:
        """Its workers' log files: the files of the launcher's log folder whose names hold the job's id as a word
        (``812_3.log``, ``ssh-4711.0_1.log``); none written yet: none."""
        folder = self.launcher.logs(self.launcher.cfg)
        word = re.compile(rf"(?<![0-9A-Za-z])(?<![0-9]\.){re.escape(self.id)}(?![0-9A-Za-z]|\.[0-9])")
        return sorted(p for p in folder.rglob("*.log") if word.search(p.name)) if folder.is_dir() else []


def state_of(workers: Sequence[Workers]) -> str:
    """A job's state from its workers: RUNNING (one runs), PENDING (all queued), ENDING (all being stopped), DONE
    (none left), or the launcher's own word where they share one."""
    states = {"ENDING" if w.ending else w.state for w in workers}
    if not states:
        return "DONE"
    return states.pop() if len(states) == 1 else ("RUNNING" if "RUNNING" in states else sorted(states)[0])


def submission_id(launcher: Launcher, job: Any) -> str:
    """The id of what ``launcher.submit`` returned, refused in one line unless it is a ``Job``."""
    if not isinstance(job, Job):
        raise BronchoError(f"launcher {launcher.name}: submit returned {type(job).__name__} {job!r}, not a Job "
                           "(return self.Job(self, id): docs/sweep.md, \"Adding a launcher\")")
    return job.id


class WorkerEnvironment:
    """The worker side of a launcher: what a worker it started asks about itself (submitit's JobEnvironment). Built
    in the worker's process from the launcher's validated settings (``Launcher.environment``). The defaults: a
    worker with no job of its own, no warning signal, nothing to do at the end."""

    warning_signal: ClassVar[int | None] = None  # sent before the launcher stops the worker: it checkpoints and stops
    warning_meaning: ClassVar[str] = ""  # what sends it, as a stopped run's KILLED reason says it

    def __init__(self, settings: Any = None):
        self.settings = settings  # the launcher's ``Settings`` (None: it has none)

    @classmethod
    def detect(cls) -> bool:
        """This process runs inside a job of this launcher, whoever started it (Slurm: ``SLURM_JOB_ID`` is set):
        ``bronchopose train`` in a batch job then stops on the launcher's warning signal too."""
        return False

    @property
    def job_id(self) -> str | None:
        """This worker's id in the launcher (Slurm: ``812_3``), recorded in its ``WorkerId``; None: none."""
        return None

    @property
    def task_index(self) -> int | None:
        """This worker's index among its submission's (Slurm: ``SLURM_ARRAY_TASK_ID``); None: not known."""
        return None

    @property
    def threads(self) -> int | None:
        """The CPU threads this worker was given (Slurm: ``SLURM_CPUS_PER_TASK``); None: the config decides."""
        return None

    @property
    def exits_when_idle(self) -> bool:
        """Exit when nothing is claimable now instead of waiting for cells held elsewhere."""
        return True

    def warned(self, requested: int | None) -> bool:
        """The stop signal ``requested`` is this launcher's warning (the launcher itself replaces the worker)."""
        return requested is not None and requested == self.warning_signal

    def requeue(self) -> bool:
        """Put this worker back in the launcher's queue; whether it was (default: it cannot be)."""
        return False

    def done(self, requested: int | None) -> None:
        """After the worker loop; ``requested``: the stop signal it received (None: it ran out of work)."""


class Launcher(ABC):
    """One way of starting a sweep's workers. Subclass it in one module, then register it
    (``launchers.register``)."""

    name: ClassVar[str]
    Settings: ClassVar[type[Section] | None] = None  # the model of its section sweep.launchers.<name>; None: none
    Environment: ClassVar[type[WorkerEnvironment]] = WorkerEnvironment  # the worker side
    Session: ClassVar[type[Session]] = Session  # the submitting command's side (sweep.session): workers outlive it
    Job: ClassVar[type[Job]] = Job  # one submission: its state, cancel and logs (a launcher's own writes ``cancel``)
    parameters: ClassVar[Mapping[str, Parameter]] = {}  # the options its __init__ takes: GENERIC or <name>_<option>

    def __init__(self, cfg: Config, command: Sequence[str] | Callable[[], Sequence[str]] = (), *, only: Any = None,
                 runner: Any = None, study: Any = None, **given: Any):
        """How ``sweep run`` and ``tune`` build the launcher they drive. ``command``: what each worker runs
        (``task.command``: ``python -m bronchocli.sweep.task <spec>``), or the function that makes it, called at the
        first use of ``self.command`` (making it seals the spec: a 0600 secrets file where the config holds secrets;
        a launcher whose workers never run it never makes it). ``only``, ``runner``, ``study``: what its workers work
        on, as the command was given them (a launcher whose workers run ``command`` has them in its spec too).
        ``given``: the values given for its ``parameters`` (those given only, each checked against its
        ``Parameter``); a launcher with parameters of its own takes them by name in its ``__init__``."""
        self.cfg, self._command = cfg, command
        self.only, self.runner, self.study, self.given = only, runner, study, given

    @property
    @final
    def command(self) -> list[str]:
        """What each worker runs (made once, at its first use)."""
        if callable(self._command):
            self._command = list(self._command())
        return list(self._command)

    # -- the submitting side -------------------------------------------------------------------------------
    @abstractmethod
    def submit(self, n: int, stage: str, after: Sequence[str] = ()) -> Job:
        """Start ``n`` workers for the stages up to ``stage``, once the submissions ``after`` (their ids) have
        ended; the submission (``self.Job(self, id)``)."""

    @abstractmethod
    def active(self) -> list[Workers]:
        """This sweep's workers still queued or running."""

    @final
    def jobs(self) -> list[Job]:
        """This sweep's submissions with workers still queued or running, in the order they were made."""
        return [self.Job(self, j) for j in sorted({w.job for w in self.active()}, key=job_order)]

    @final
    def cancel(self, dry_run: bool = False) -> list[Job]:
        """Stop every submission of this sweep (each ``Job.cancel``); the jobs stopped (``dry_run``: would be;
        nothing is stopped)."""
        jobs = self.jobs()
        if not dry_run:
            for job in jobs:
                job.cancel()
        return jobs

    def describe(self) -> str:
        """One line: where the workers run and where their logs are."""
        return f"launcher {self.name}, logs {self.logs(self.cfg)}"

    def check(self) -> None:
        """Refuse (one line, ``BronchoError``) what would make every worker fail, before anything is created."""

    def capacity(self, runnable: int) -> int:
        """Workers worth starting for ``runnable`` cells (each works through cells until none is claimable)."""
        return max(0, runnable)

    # -- provided, not overridden (``typing.final``): what its settings say -----------------------------------
    @final
    @classmethod
    def settings(cls, cfg: Config) -> Any:
        """Its section ``sweep.launchers.<name>`` validated against ``Settings`` (its defaults when absent):
        ConfigError naming ``sweep.launchers.<name>.<key>``, the value and what is allowed. None: no model."""
        if cls.Settings is None:
            if cfg.sweep.launchers.get(cls.name):
                raise ConfigError(f"sweep.launchers.{cls.name}: launcher {cls.name} takes no settings; remove it")
            return None
        return cfg.launcher_settings(cls.name, cls.Settings)

    @final
    @classmethod
    def environment(cls, cfg: Config) -> WorkerEnvironment:
        """The worker side, inside a worker this launcher started (its settings validated)."""
        return cls.Environment(cls.settings(cfg))

    @final
    @classmethod
    def logs(cls, cfg: Config) -> Path:
        """The folder of its workers' logs (and of a sealed spec's 0600 secrets file): its setting ``logs`` where
        its ``Settings`` declare one (resolved as the core config's folders are), else ``sweep.logs/<sweep>``."""
        folder = getattr(cls.settings(cfg), SETTING_LOGS, None)
        if not folder:
            return cfg.paths.sweep_logs / cfg.name
        return output_folder(cfg, folder, f"sweep.launchers.{cls.name}.{SETTING_LOGS}")

    @final
    @classmethod
    def roots(cls, cfg: Config) -> list[tuple[str, Path]]:
        """Output folders of its own settings (setting name, folder) that must not hold, or sit inside, another
        output root (``config.check_roots``): its ``logs`` setting's folder, where it declares one."""
        if not getattr(cls.settings(cfg), SETTING_LOGS, None):
            return []  # under sweep.logs, which the core config checks
        return [(f"sweep.launchers.{cls.name}.{SETTING_LOGS}", cls.logs(cfg))]

    @final
    @classmethod
    def python(cls, cfg: Config) -> str:
        """The interpreter its workers run: its setting ``python`` where its ``Settings`` declare one and it is
        set, else the one running this command."""
        return getattr(cls.settings(cfg), SETTING_PYTHON, None) or sys.executable


def words(kind: type[Launcher]) -> tuple[str, str, str]:
    """What messages call launcher ``kind`` and its workers: (title, one submission, one worker), e.g. ("Slurm",
    "Slurm array job", "task"); its ``Session`` says them."""
    return kind.Session.words(kind.name)
