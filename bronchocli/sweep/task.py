"""A detached sweep worker: ``python -m bronchocli.sweep.task '<spec>'`` (a Slurm array task, or a worker of any
launcher whose workers outlive the command) runs the one worker entry, ``stagework.worker_main``.

The command that submits the workers (``entry.run``; ``tuning.launch.tune`` for a study's) writes the spec
(``command``), a small JSON object
(``TaskSpec``: the config file, profile, ``--set`` overrides, ``--storage``,
``--use-tuned``, ``--only``, ``--runner``, the launcher's name, and for a
tuning study's workers the study: they claim its trial rows), into the
worker's command (Slurm: the batch script's ``exec`` line). A value that holds a
password (a ``--set`` override or ``--storage`` URL, in any form ``urls.redact``
knows) is never written there nor onto the worker's command line (``ps`` shows
it to every user): ``seal`` moves those values into a file only the user can
read (mode 0600, beside the launcher's logs) and the spec shows them redacted
and names that file. The worker loads the same config the same way
(``TaskSpec.load``, which the ``sweep`` command itself uses), checks its paths
and works the stages up to the one it was submitted for (``launchers.STAGE_ENV``,
set by its launcher); it exits when nothing is left there that it can claim.
What else its launcher does (Slurm: SIGUSR1 then ``scontrol requeue``) is the
launcher's worker side (``Launcher.Environment``).

A user error (bad config, unreachable storage) is one line on stderr (the worker's
log) and exit code 2, as on the command line.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import logging
import os
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

from .. import urls
from ..cells import Selection, parse_only
from ..config import Config, check_paths, load_config
from ..errors import BronchoError
from ..io import write_text
from .launchers import STAGE_ENV, launcher_class, log_roots
from .stagework import WorkerJob, worker_config, worker_main
from .tuning.rows import StudyTask
from .worker import Runner, default_runner

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
    launcher: str | None = None  # the launcher that starts the workers (its worker side); set by ``launch``
    study: str | None = None  # a tuning study's workers (``bronchopose tune``): its trial rows, not the stages
    deadline: float | None = None  # ... and when its trials stop starting (epoch seconds, ``tune --timeout``)
    secrets: str | None = None  # a 0600 file holding the real overrides/storage (``seal``); these are redacted

    def load(self) -> Config:
        """The config: file + profile + overrides, then the storage URL and a study's best trial."""
        spec = self.unsealed()
        cfg = load_config(Path(spec.config), spec.profile, spec.overrides)
        if spec.storage:
            cfg = cfg.with_values({"storage.url": spec.storage})
        if self.use_tuned:  # new values -> new cell keys: tuned cells never reuse untuned runs
            from .tuning.studies import apply_best  # lazy: optuna only with --use-tuned

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
                               "again (`bronchopose sweep run --launcher NAME` writes it)") from None
        except (ValueError, KeyError, TypeError):
            raise BronchoError(f"task spec: secret file {self.secrets}: not what `bronchopose sweep run "
                               "--launcher NAME` writes; submit the sweep again") from None

    def seal(self, folder: Path) -> TaskSpec:
        """This spec with every value that holds a password moved into a file in ``folder`` that only this user
        can read (0600); the spec keeps them redacted and names the file. Unchanged when nothing is secret."""
        if not any(urls.has_secret(v) for v in (*self.overrides, self.storage or "")):
            return self
        text = json.dumps({"overrides": list(self.overrides), "storage": self.storage}, sort_keys=True)
        path = folder / f"secrets-{hashlib.sha256(text.encode()).hexdigest()[:16]}.json"  # same values: same file
        write_text(path, text, private=True)
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


def command(cfg: Config, spec: TaskSpec, logs: Path | None = None) -> list[str]:
    """What each detached worker runs: its launcher's Python (``Launcher.python``: Slurm's ``python`` setting, else
    this one) on this module with ``spec``, its secrets sealed into a 0600 file in ``logs`` (default: the
    launcher's log folder), never in a script or the argv."""
    kind = launcher_class(_launcher(spec.launcher), "task spec: launcher")
    spec = replace(spec, config=str(Path(spec.config).resolve())).seal(logs or kind.logs(cfg))
    return [kind.python(cfg), "-m", MODULE, spec.to_json()]


def main(argv: Sequence[str] | None = None) -> int:
    """The worker's entry point: load the spec's config, check it, run the worker; exit code like a worker's."""
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        if len(args) != 1:
            raise BronchoError(f"usage: python -m {MODULE} '<task spec JSON>' (written by `bronchopose sweep run "
                               "--launcher NAME` into the worker's command)")
        spec = TaskSpec.from_json(args[0])
        cfg = spec.load()
        only, runner = spec.selection(), spec.cell_runner()
        kind = launcher_class(_launcher(spec.launcher), "task spec: launcher")
        check_paths(cfg, storage=True, logs=True, extra=log_roots(cfg, kind))
        study = StudyTask(spec.study, cfg.name, spec.deadline) if spec.study else None
        return run_task(cfg, only, runner, _launcher(spec.launcher), study)
    except BronchoError as exc:
        sys.stderr.write(f"error: {urls.redact(str(exc))}\n")  # a setting may be a URL with a password
        return exc.exit_code


def _launcher(name: str | None) -> str:
    if not name:
        raise BronchoError("task spec: no launcher named; submit the sweep again (`bronchopose sweep run --launcher "
                           "NAME` names it)")
    return name


def run_task(cfg: Config, only: Selection, runner: Runner, launcher: str, study: StudyTask | None = None) -> int:
    """One detached worker of ``launcher`` through the stages up to ``STAGE_ENV``'s, or through a study's trial
    rows (``study``) (``stagework.worker_main``)."""
    kind = launcher_class(launcher, "task spec: launcher")
    job = WorkerJob(worker_config(cfg), cfg.paths.storage_url, only, kind, runner,
                    last_stage=os.environ.get(STAGE_ENV) or None, exit_when_idle=kind.environment(cfg).exits_when_idle,
                    study=study)
    return worker_main(job)


if __name__ == "__main__":  # the worker's log gets every log line; set up here, not by the library call
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    sys.exit(main())
