"""Launchers: where a sweep's workers run (the protocol: ``base.Launcher``; docs/sweep.md, "Launchers").

- ``local``: child processes of the command, pinned to this machine's GPUs (``local.LocalLauncher``);
- ``slurm``: Slurm job arrays, one worker per array task (``slurm.SlurmLauncher``; docs/cluster.md).

Adding a launcher is one module with a ``Launcher`` subclass, found by name in one of three ways: a ``register``
call (below, or in the module that defines it); an entry point of the group ``bronchopose.launchers`` in any
installed package (``NAME = "package.module:Class"``: nothing in this repository changes); or ``module:Class``
itself. ``bronchopose sweep run --launcher NAME`` and ``sweep.launcher`` then name it, and its own settings are
``sweep.launchers.NAME`` (docs/sweep.md, "Adding a launcher"). The options it takes are its ``parameters``
(``GENERIC`` ones, or ``NAME_<option>``), checked when it is registered; ``sweep run`` offers a flag for each
parameter of every launcher that loads.
"""

from __future__ import annotations

import importlib
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path

from ...config import Config
from ...errors import DEBUG_HINT, BronchoError, ConfigError
from .base import (GENERIC, STAGE_ENV, Job, Launcher, Parameter, WorkerEnvironment, Workers, check_declarations, flag,
                   words)
from .local import LocalLauncher
from .slurm import SlurmLauncher

_LAUNCHERS: dict[str, type[Launcher]] = {}
GROUP = "bronchopose.launchers"  # the entry-point group of launchers that installed packages provide


def register(cls: type[Launcher]) -> type[Launcher]:
    """Make ``cls`` a launcher that ``--launcher cls.name`` names (usable as a class decorator); its ``parameters``
    and its ``Job`` are checked first (one line naming the launcher: ``base.check_declarations``)."""
    if not isinstance(cls, type) or not issubclass(cls, Launcher):
        raise BronchoError(f"launcher {cls!r}: must be a subclass of sweep.launchers.Launcher")
    check_declarations(cls)
    _LAUNCHERS[cls.name] = cls
    return cls


def _entry_points() -> dict[str, EntryPoint]:
    return {ep.name: ep for ep in entry_points(group=GROUP)}


def names() -> list[str]:
    """The registered launchers, then those installed packages offer (entry points) not loaded yet."""
    return [*_LAUNCHERS, *(n for n in _entry_points() if n not in _LAUNCHERS)]


def launcher_class(name: str, what: str = "--launcher") -> type[Launcher]:
    """The launcher ``name``: a registered one, else an installed package's entry point of that name (group
    ``bronchopose.launchers``), else ``module:Class`` (how a detached worker finds a launcher defined outside this
    package); loaded ones are registered. One line naming the known ones when there is none."""
    if name in _LAUNCHERS:
        return _LAUNCHERS[name]
    if (ep := _entry_points().get(name)) is not None:
        try:
            cls = ep.load()
        except Exception as exc:  # noqa: BLE001 - a plugin's import may raise anything: one line naming it
            raise BronchoError(f"{what} {name}: entry point {ep.name} = {ep.value} (group {GROUP}) cannot be loaded: "
                               f"{_exception(exc)}{DEBUG_HINT}") from exc
        if getattr(cls, "name", None) != name:
            raise BronchoError(f"{what} {name}: entry point {ep.value} is launcher {getattr(cls, 'name', cls)!r}, "
                               f"not {name!r}; name the entry point as the class names itself")
        return register(cls)
    module, _, attr = name.partition(":")
    if module and attr:
        try:
            return register(getattr(importlib.import_module(module), attr))
        except Exception as exc:  # noqa: BLE001 - a plugin's import may raise anything: one line naming it
            raise BronchoError(f"{what} {name}: module {module} cannot be loaded: {_exception(exc)}{DEBUG_HINT}"
                               ) from exc
    raise BronchoError(f"{what} {name}: must be one of {', '.join(names())}")


def _exception(exc: BaseException) -> str:
    """``RuntimeError: message`` in one line (a SyntaxError's file and line included)."""
    where = f" ({exc.filename}, line {exc.lineno})" if isinstance(exc, SyntaxError) and exc.filename else ""
    text = str(exc.msg if isinstance(exc, SyntaxError) else exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}{where}".rstrip(": ")


def loadable(names_: list[str]) -> list[type[Launcher]]:
    """The launchers of ``names_`` that load (a broken plugin is left out: it is said when it is named)."""
    out = []
    for name in names_:
        try:
            out.append(launcher_class(name))
        except BronchoError:
            continue
    return out


def parameters(generic_only: bool = False) -> dict[str, Parameter]:
    """Every option of the launchers that load (name -> ``Parameter``): the generic ones first and once, then each
    launcher's own (a broken plugin is left out: it is said when it is named); ``generic_only``: ``GENERIC``."""
    out = dict(GENERIC)
    for kind in [] if generic_only else loadable(names()):
        out.update({name: p for name, p in kind.parameters.items() if name not in out})
    return out


def owners(name: str) -> list[str]:
    """The launchers that load and take the parameter ``name``."""
    return [k.name for k in loadable(names()) if name in k.parameters]


def detected() -> type[WorkerEnvironment] | None:
    """The worker environment of the launcher whose job this process runs in (``detect``), else None: every
    launcher is asked, the registered ones and those installed packages offer through entry points (loaded here;
    one that does not load is left out), as submitit's ``JobEnvironment`` asks each plugin whether it is active."""
    return next((k.Environment for k in loadable(names()) if k.Environment.detect()), None)


def log_roots(cfg: Config, kind: type[Launcher] | None = None) -> list[tuple[str, Path]]:
    """The output roots of the launchers' own settings (``Launcher.roots``) for the checks made before a command
    writes anything (``config.check_paths(extra=...)``): ``kind``'s (default: ``sweep.launcher``'s) and those of
    every launcher with a section in ``sweep.launchers``, each section validated (one line naming its key; a
    section of no known launcher is refused with the known names)."""
    kinds = {k.name: k for k in [kind or launcher_class(cfg.sweep.launcher, "sweep.launcher")]}
    for section in cfg.sweep.launchers:
        if section not in kinds:
            try:
                kinds[section] = launcher_class(section, f"sweep.launchers.{section}:")
            except BronchoError:
                if section in names():  # installed, but its code does not load: that error, not "no launcher"
                    raise
                raise ConfigError(f"sweep.launchers.{section}: no launcher of that name (known: {', '.join(names())}; "
                                  "a section is named as its launcher names itself)") from None
    out = []
    for k in kinds.values():
        k.settings(cfg)
        out += k.roots(cfg)
    return out


def reference(cls: type[Launcher]) -> str:
    """What a worker's spec names ``cls`` by: its name when this package registers it, else ``module:Class``."""
    return cls.name if cls.__module__.startswith(__name__ + ".") else f"{cls.__module__}:{cls.__qualname__}"


register(LocalLauncher)
register(SlurmLauncher)

__all__ = ["GENERIC", "GROUP", "STAGE_ENV", "Job", "Launcher", "LocalLauncher", "Parameter", "SlurmLauncher",
           "WorkerEnvironment", "Workers", "detected", "flag", "launcher_class", "loadable", "log_roots", "names",
           "owners", "parameters", "reference", "register", "words"]
