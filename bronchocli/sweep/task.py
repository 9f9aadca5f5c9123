"""A Slurm array task: ``python -m bronchocli.sweep.task '<spec>'`` runs one sweep worker through the stages.

The launcher (``entry.launch_slurm``) writes the spec, a small JSON object
(``TaskSpec``: the config file, profile, ``--set`` overrides, ``--storage``,
``--use-tuned``, ``--only`` and ``--runner`` it was given), into the batch
script's ``exec`` line. A value that holds a password (a ``--set`` override or
``--storage`` URL, in any form ``urls.redact`` knows) is never written there nor
onto the task's command line (``ps`` shows it to every user): ``seal`` moves
those values into a file only the user can read (mode 0600, beside the task
logs) and the spec shows them redacted and names that file. The task loads the same config the same way
(``TaskSpec.load``, which the ``sweep`` command itself uses), checks its paths
and runs one worker over the stage walk (``staged.work_stages``) up to the stage
its array was submitted for (``slurm.STAGE_ENV``, set by the batch script); it
exits when nothing is left there that it can claim. On SIGUSR1 (Slurm's time-limit warning,
``--signal=B:USR1@<s>``) the worker gives its cell back and the task requeues
itself (``slurm.requeue``).

A user error (bad config, unreachable storage) is one line on stderr (the task
log) and exit code 2, as on the command line.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import logging
import os
import signal
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

from .. import urls
from ..cells import Selection, parse_only
from ..config import Config, check_paths, load_config
from ..errors import BronchoError
from .pool import worker_config
from .slurm import STAGE_ENV, logs_dir, requeue
from .staged import work_stages
from .storage import SweepStore
from .worker import EXIT_INTERRUPTED, Runner, StopSignals, default_runner, slurm_task

log = logging.getLogger(__name__)

MODULE = "bronchocli.sweep.task"  # what ``python -m`` runs (``__name__`` is ``__main__`` there)


def load_runner(spec: str | None) -> Runner:
    """The cell runner named ``module:function`` (``--runner``); None: ``default_runner`` (training)."""
    if not spec:
        return default_runner
    module, _, name = spec.partition(":")
    if not module or not name:
        raise BronchoError(f"--runner {spec}: must be module:function (a function with run_cell's signature)")
    try:
        fn = getattr(importlib.import_module(module), name)
    except ImportError as exc:
        raise BronchoError(f"--runner {spec}: cannot import {module} ({exc}); it must be importable by the "
                           "workers (e.g. on PYTHONPATH)") from None
    except AttributeError:
        raise BronchoError(f"--runner {spec}: module {module} has no {name}") from None
    if not callable(fn):
        raise BronchoError(f"--runner {spec}: {name} is not a function")
    return fn


@dataclass(frozen=True)
class TaskSpec:
    """How a sweep's config is loaded and what its workers run: enough for a task on another node to agree."""

    config: str  # experiments.yaml (made absolute in the task's command)
    profile: str | None = None
    overrides: tuple[str, ...] = ()  # --set key=value
    storage: str | None = None  # --storage (as given: ${PGPASSWORD} is expanded where it is used)
    use_tuned: str | None = None
    only: tuple[str, ...] = ()  # --only texts
    runner: str | None = None  # --runner module:function; None: training
    secrets: str | None = None  # a 0600 file holding the real overrides/storage (``seal``); these are redacted

    def load(self) -> Config:
        """The config: file + profile + overrides, then the storage URL and a study's best trial."""
        spec = self.unsealed()
        cfg = load_config(Path(spec.config), spec.profile, spec.overrides)
        if spec.storage:
            cfg = cfg.with_values({"storage.url": spec.storage})
        if self.use_tuned:  # new values -> new cell keys: tuned cells never reuse untuned runs
            from .tuning import apply_best  # lazy: optuna only with --use-tuned

            cfg = apply_best(cfg, self.use_tuned)
        return cfg

    def unsealed(self) -> TaskSpec:
        """This spec with the values ``seal`` moved into its secret file put back (itself when none was)."""
        if not self.secrets:
            return self
        try:
            data = json.loads(Path(self.secrets).read_text())
            return replace(self, overrides=tuple(data["overrides"]), storage=data["storage"], secrets=None)
        except OSError as exc:
            raise BronchoError(f"task spec: secret file {self.secrets}: {exc.strerror or exc}; submit the sweep "
                               "again (`bronchopose sweep --launcher slurm` writes it)") from None
        except (ValueError, KeyError, TypeError):
            raise BronchoError(f"task spec: secret file {self.secrets}: not what `bronchopose sweep --launcher "
                               "slurm` writes; submit the sweep again") from None

    def seal(self, folder: Path) -> TaskSpec:
        """This spec with every value that holds a password moved into a file in ``folder`` that only this user
        can read (0600); the spec keeps them redacted and names the file. Unchanged when nothing is secret."""
        if not any(urls.has_secret(v) for v in (*self.overrides, self.storage or "")):
            return self
        text = json.dumps({"overrides": list(self.overrides), "storage": self.storage}, sort_keys=True)
        path = folder / f"secrets-{hashlib.sha256(text.encode()).hexdigest()[:16]}.json"  # same values: same file
        write_private(path, text)
        return replace(self, overrides=tuple(urls.redact(v) for v in self.overrides),
                       storage=urls.redact(self.storage) if self.storage else None, secrets=str(path))

    def selection(self) -> Selection:
        return parse_only(list(self.only))

    def cell_runner(self) -> Runner:
        return load_runner(self.runner)

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> TaskSpec:
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise BronchoError(f"task spec: not JSON ({exc})") from None
        known = {f.name for f in fields(cls)}
        if not isinstance(data, dict) or "config" not in data or set(data) - known:
            raise BronchoError(f"task spec: must be an object with 'config' and only {', '.join(sorted(known))}")
        for key in ("overrides", "only"):
            data[key] = tuple(data.get(key) or ())
        return cls(**data)


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically, readable and writable by this user only (0600) from its first byte."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)  # the file existed (a crashed earlier write): O_CREAT's mode does not apply
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def command(cfg: Config, spec: TaskSpec) -> list[str]:
    """What each array task runs: the config's ``slurm.python`` (else this Python) on this module with ``spec``,
    its secrets sealed into a 0600 file beside the task logs (never in the batch script or the argv)."""
    spec = replace(spec, config=str(Path(spec.config).resolve())).seal(logs_dir(cfg))
    return [cfg.slurm.python or sys.executable, "-m", MODULE, spec.to_json()]


def run_task(cfg: Config, store: SweepStore, only: Selection, runner: Runner = default_runner) -> int:
    """One worker through the stages; on SIGUSR1 (the time-limit warning) it gives its cell back and the task
    requeues itself."""
    threads = os.environ.get("SLURM_CPUS_PER_TASK")
    wcfg = worker_config(cfg, 1)
    if cfg.train.threads is None and threads and threads.isdigit():
        wcfg = wcfg.with_values({"train.threads": int(threads)})
    signals = StopSignals()
    signals.install(extra=(signal.SIGUSR1,))
    log.info("sweep worker %s, Slurm task %s, CUDA_VISIBLE_DEVICES=%s", cfg.name, slurm_task(),
             os.environ.get("CUDA_VISIBLE_DEVICES", "unset"))
    try:
        code = work_stages(wcfg, store, only, signals=signals, runner=runner, exit_when_idle=cfg.slurm.exit_when_idle,
                           last_stage=os.environ.get(STAGE_ENV) or None)
    except KeyboardInterrupt:
        code = EXIT_INTERRUPTED
    if signals.requested == signal.SIGUSR1 and (task := slurm_task()):
        if cfg.slurm.on_time_limit == "requeue":
            log.info("time limit near: requeueing Slurm task %s", task)
            requeue(task)
        else:
            log.info("time limit near: Slurm task %s exits (slurm.on_time_limit: exit); a new task takes the cell",
                     task)
    return code


def main(argv: Sequence[str] | None = None) -> int:
    """The task's entry point: load the spec's config, check it, run the worker; exit code like a worker's."""
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        if len(args) != 1:
            raise BronchoError(f"usage: python -m {MODULE} '<task spec JSON>' (written by `bronchopose sweep "
                               "--launcher slurm` into the batch script)")
        spec = TaskSpec.from_json(args[0])
        cfg = spec.load()
        only, runner = spec.selection(), spec.cell_runner()
        check_paths(cfg, storage=True, logs=True)
        store = SweepStore(cfg.paths.storage_url, cfg.runs.timeout_s, cfg.runs.busy_timeout_s)
        return run_task(cfg, store, only, runner)
    except BronchoError as exc:
        sys.stderr.write(f"error: {urls.redact(str(exc))}\n")  # a setting may be a URL with a password
        return exc.exit_code


if __name__ == "__main__":  # the task log gets every worker's log line; set up here, not by the library call
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    sys.exit(main())
