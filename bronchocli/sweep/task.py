"""A Slurm array task: ``python -m bronchocli.sweep.task '<spec>'`` runs one sweep worker through the stages.

The launcher (``entry.launch_slurm``) writes the spec, a small JSON object
(``TaskSpec``: the config file, profile, ``--set`` overrides, ``--storage``,
``--use-tuned``, ``--only`` and ``--runner`` it was given), into the batch
script's ``exec`` line. The task loads the same config the same way
(``TaskSpec.load``, which the ``sweep`` command itself uses), checks its paths
and runs one worker over the stage walk (``staged.work_stages``); it exits when
nothing is left that it can claim. On SIGUSR1 (Slurm's time-limit warning,
``--signal=B:USR1@<s>``) the worker gives its cell back and the task requeues
itself (``slurm.requeue``).

A user error (bad config, unreachable storage) is one line on stderr (the task
log) and exit code 2, as on the command line.
"""

from __future__ import annotations

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
from .slurm import requeue
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

    def load(self) -> Config:
        """The config: file + profile + overrides, then the storage URL and a study's best trial."""
        cfg = load_config(Path(self.config), self.profile, self.overrides)
        if self.storage:
            cfg = cfg.with_values({"storage.url": self.storage})
        if self.use_tuned:  # new values -> new cell keys: tuned cells never reuse untuned runs
            from .tuning import apply_best  # lazy: optuna only with --use-tuned

            cfg = apply_best(cfg, self.use_tuned)
        return cfg

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


def command(cfg: Config, spec: TaskSpec) -> list[str]:
    """What each array task runs: the config's ``slurm.python`` (else this Python) on this module with ``spec``."""
    spec = replace(spec, config=str(Path(spec.config).resolve()))
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
        code = work_stages(wcfg, store, only, signals=signals, runner=runner, exit_when_idle=cfg.slurm.exit_when_idle)
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
