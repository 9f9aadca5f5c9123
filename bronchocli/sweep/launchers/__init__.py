"""Launchers: where a sweep's workers run (the protocol: ``base.Launcher``; docs/sweep.md, "Launchers").

- ``local``: child processes of the command, pinned to this machine's GPUs (``local.LocalLauncher``);
- ``slurm``: Slurm job arrays, one worker per array task (``slurm.SlurmLauncher``; docs/cluster.md).

Adding a launcher is one module with a ``Launcher`` subclass, found by name in one of three ways: a ``register``
call (below, or in the module that defines it); an entry point of the group ``bronchopose.launchers`` in any
installed package (``NAME = "package.module:Class"``: nothing in this repository changes); or ``module:Class``
itself. ``bronchopose sweep run --launcher NAME`` and ``sweep.launcher`` then name it, and its own settings are
``sweep.launchers.NAME`` (docs/sweep.md, "Adding a launcher").
"""

from __future__ import annotations

import importlib
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path

from ...config import Config
from ...errors import DEBUG_HINT, BronchoError, ConfigError
from .base import STAGE_ENV, Launcher, WorkerEnvironment, Workers, words
from .local import LocalLauncher
from .slurm import SlurmLauncher

_LAUNCHERS: dict[str, type[Launcher]] = {}
GROUP = "bronchopose.launchers"  # the entry-point group of launchers that installed packages provide


def register(cls: type[Launcher]) -> type[Launcher]:
    """Make ``cls`` a launcher that ``--launcher cls.name`` names (usable as a class decorator)."""
    if not isinstance(cls, type) or not issubclass(cls, Launcher):
        raise BronchoError(f"launcher {cls!r}: must be a subclass of sweep.launchers.Launcher")
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

__all__ = ["GROUP", "STAGE_ENV", "Launcher", "LocalLauncher", "SlurmLauncher", "WorkerEnvironment", "Workers",
           "detected", "launcher_class", "loadable", "log_roots", "names", "reference", "register", "words"]
