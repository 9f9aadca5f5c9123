"""The launcher protocol: where a sweep's workers run, and nothing about which cell each runs.

A launcher starts, lists and stops *workers*; the claims table still decides
which cell each worker runs, exactly once (docs/sweep.md, "Launchers"). The
protocol follows submitit's ``Executor`` (submit jobs, find them again, cancel
them) with the sweep's claims model in place of job results:

- ``submit(n, stage, after)``: start ``n`` workers that work the stages up to
  ``stage`` (the worker entry ``stagework.worker_main``, told the stage in
  ``STAGE_ENV``), started only once the submissions ``after`` have ended;
  returns the submission's id;
- ``active()``: this sweep's workers still queued or running, as ``Workers``
  groups (a submission's id, its stage, how many);
- ``cancel(dry_run)``: stop every worker of this sweep (they release their
  cells); returns the submissions stopped (``dry_run``: those it would stop);
- ``describe()``: one line saying where the workers run and where they log.

What a launcher needs beyond that has a default: ``parameters`` (the options it takes: name -> ``Parameter``,
submitit's executor parameters; ``sweep run --<name-with-dashes>`` on the command line, keywords of
``bronchocli.api``; a name is ``GENERIC`` or ``<launcher name>_<option>``), ``create`` (built for ``sweep run``
with the values given for its ``parameters``), ``check`` (refuse what would make workers fail, before anything is
created), ``capacity`` (workers worth starting for ``runnable`` cells), ``follow`` (make queued later-stage
submissions wait for a new earlier one), ``tick`` (called on every refresh of the watch). The driver
(``sweep.launch``) asks a few more things and never the launcher's name: ``supervised`` (the block its
workers live in: the local launcher's Ctrl-C stops them there), ``wait`` (until something may have
changed), ``stopped`` (its workers were told to stop), ``exit_codes`` (how the workers that ended
exited, where it can tell), ``defers`` (a later stage's submission can wait for the earlier ones:
without it one stage is submitted at a time) and ``resubmits`` (workers that ended with cells left
are replaced: they were cancelled or timed out; without it they stopped for a reason a new worker
would meet too), ``runs_command`` (its workers run ``command``), ``poll_s`` (how often the watch asks)
and ``submitted`` (the line announcing a submission).

What a launcher owns besides: ``Settings``, the model of its own config section ``sweep.launchers.<name>``
(validated by ``settings(cfg)`` when the launcher is looked up; the core config holds it as a plain mapping),
``logs`` (its workers' log folder) and ``roots`` (folders of its settings that no other output root may hold),
and ``Environment``, the worker side (submitit's JobEnvironment): built inside a worker it started
(``environment(cfg)``), it says the worker's job id and task index, the CPU threads it was given, whether it exits
when idle, the launcher's *warning signal* (Slurm: SIGUSR1 before the time limit; training stops on it and
checkpoints, ``interrupts.warned_by``) and what the worker does after its loop (``done``: Slurm ``requeue``s a task
warned of its time limit).

``detachable``: the workers outlive the command that submitted them (``sweep run --detach``, ``sweep
cancel``); the local launcher's do not (its workers are the command's own child processes).
"""

from __future__ import annotations

import re
import sys
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from ...config import Config, Section
from ...config.arguments import RULES, Rule
from ...errors import BronchoError, ConfigError

STAGE_ENV = "BRONCHOPOSE_SWEEP_STAGE"  # the stage a worker was submitted for: it stops after that stage


@dataclass(frozen=True)
class Parameter:
    """One option a launcher takes, as its ``Launcher.parameters`` declares it: ``--<name-with-dashes>`` on ``sweep
    run`` and ``tune``, ``<name>=`` in ``bronchocli.api``, ``<name>=`` of its ``create``. ``type``: int, float, str,
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


def check_parameters(cls: type[Launcher]) -> None:
    """Refuse, in one line naming the launcher and the parameter, a ``parameters`` entry that is neither a generic
    name declared as ``GENERIC`` has it nor ``<launcher name>_<option>`` with a ``Parameter``."""
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
    detachable: ClassVar[bool] = True
    title: ClassVar[str] = ""  # how messages name it ("Slurm"; default: its name)
    job_word: ClassVar[str] = "job"  # one submission in messages ("Slurm array job")
    task_word: ClassVar[str] = "worker"  # one worker in messages ("task")
    Settings: ClassVar[type[Section] | None] = None  # the model of its section sweep.launchers.<name>; None: none
    Environment: ClassVar[type[WorkerEnvironment]] = WorkerEnvironment  # the worker side
    parameters: ClassVar[Mapping[str, Parameter]] = {}  # the options it takes (``create``): GENERIC or <name>_<option>
    runs_command: ClassVar[bool] = True  # its workers run ``command`` (the local launcher's get their job by spawn)
    defers: ClassVar[bool] = True  # ``submit(after=...)`` makes a later stage wait; else one stage at a time
    resubmits: ClassVar[bool] = True  # workers that ended with cells left are replaced (see the module)
    poll_s: ClassVar[float] = 1.0  # how often the watch asks ``active``

    def __init__(self, cfg: Config, command: Sequence[str] = ()):
        """``command``: what each worker runs (``task.command``: ``python -m bronchocli.sweep.task <spec>``)."""
        self.cfg, self.command = cfg, list(command)

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        if "name" in cls.__dict__ and "title" not in cls.__dict__:
            cls.title = cls.name
        if "name" in cls.__dict__ and "job_word" not in cls.__dict__:
            cls.job_word = f"{cls.title} job"

    @classmethod
    def create(cls, cfg: Config, *, only: Any = None, runner: Any = None, **options: Any) -> Launcher:
        """The launcher ``sweep run`` drives: ``only`` and ``runner`` as the command was given them (a launcher
        whose workers run ``command`` gets them through its spec instead), ``options``: values of ``cls.parameters``
        (the given ones only, checked against their ``Parameter``)."""
        return cls(cfg)

    # -- the submitting side -------------------------------------------------------------------------------
    @abstractmethod
    def submit(self, n: int, stage: str, after: Sequence[str] = ()) -> str:
        """Start ``n`` workers for the stages up to ``stage``, once the submissions ``after`` have ended."""

    @abstractmethod
    def active(self) -> list[Workers]:
        """This sweep's workers still queued or running."""

    @abstractmethod
    def cancel(self, dry_run: bool = False) -> list[str]:
        """Stop every worker of this sweep; the submissions stopped (``dry_run``: would be; nothing is stopped)."""

    @abstractmethod
    def describe(self) -> str:
        """One line: where the workers run and where their logs are."""

    def check(self) -> None:
        """Refuse (one line, ``BronchoError``) what would make every worker fail, before anything is created."""

    def capacity(self, runnable: int) -> int:
        """Workers worth starting for ``runnable`` cells (each works through cells until none is claimable)."""
        return max(0, runnable)

    def follow(self, queued: Sequence[str], earlier: Sequence[str]) -> None:
        """Make the ``queued`` later-stage submissions wait for the ``earlier`` ones too (a re-submitted stage)."""

    def tick(self, active: Sequence[Workers]) -> None:
        """Called on every refresh of the watch with what ``active`` listed."""

    def submitted(self, job: str, n: int, stage: str, after: Sequence[str]) -> str:
        """The line that says a submission was made."""
        return (f"submitted {self.job_word} {job}: {n} {self.task_word}(s) for stage {stage}"
                + (f", after job(s) {', '.join(after)}" if after else ""))

    @contextmanager
    def supervised(self) -> Iterator[None]:
        """The block the driver submits and watches in (default: nothing to do; Ctrl-C stops the watch only)."""
        yield

    def wait(self, timeout: float) -> None:
        """Until something may have changed (default: ``timeout`` seconds)."""
        time.sleep(timeout)

    @property
    def stopped(self) -> bool:
        """This command told its workers to stop (the local launcher's Ctrl-C): the sweep is interrupted."""
        return False

    def exit_codes(self) -> list[int | None]:
        """How the workers that ended since the last call exited, where the launcher can tell (default: none)."""
        return []

    @classmethod
    def settings(cls, cfg: Config) -> Any:
        """Its section ``sweep.launchers.<name>`` validated against ``Settings`` (its defaults when absent):
        ConfigError naming ``sweep.launchers.<name>.<key>``, the value and what is allowed. None: no model."""
        if cls.Settings is None:
            if cfg.sweep.launchers.get(cls.name):
                raise ConfigError(f"sweep.launchers.{cls.name}: launcher {cls.name} takes no settings; remove it")
            return None
        return cfg.launcher_settings(cls.name, cls.Settings)

    @classmethod
    def environment(cls, cfg: Config) -> WorkerEnvironment:
        """The worker side, inside a worker this launcher started (its settings validated)."""
        return cls.Environment(cls.settings(cfg))

    @classmethod
    def logs(cls, cfg: Config) -> Path:
        """The folder of its workers' logs (and of a sealed spec's 0600 secrets file)."""
        return cfg.paths.sweep_logs / cfg.name

    @classmethod
    def roots(cls, cfg: Config) -> list[tuple[str, Path]]:
        """Output folders of its own settings (setting name, folder) that must not hold, or sit inside, another
        output root (``config.check_roots``); default: none (``logs`` is under ``sweep.logs``)."""
        return []

    @classmethod
    def python(cls, cfg: Config) -> str:
        """The interpreter its workers run (default: the one running this command)."""
        return sys.executable
