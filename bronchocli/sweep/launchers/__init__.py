"""Launchers: where a sweep's workers run (the protocol: ``base.Launcher``; docs/sweep.md, "Launchers").

- ``local``: child processes of the command, pinned to this machine's GPUs (``local.LocalLauncher``);
- ``slurm``: Slurm job arrays, one worker per array task (``slurm.SlurmLauncher``; docs/cluster.md).

Adding a launcher is one module with a ``Launcher`` subclass and one ``register`` call (below, or in the
module that defines it); ``bronchopose sweep run --launcher NAME`` and ``sweep.launcher`` then name it.
"""

from __future__ import annotations

import importlib

from ...errors import BronchoError
from .base import STAGE_ENV, Launcher, Workers
from .local import LocalLauncher
from .slurm import SlurmLauncher

_LAUNCHERS: dict[str, type[Launcher]] = {}


def register(cls: type[Launcher]) -> type[Launcher]:
    """Make ``cls`` a launcher that ``--launcher cls.name`` names (usable as a class decorator)."""
    if not isinstance(cls, type) or not issubclass(cls, Launcher):
        raise BronchoError(f"launcher {cls!r}: must be a subclass of sweep.launchers.Launcher")
    _LAUNCHERS[cls.name] = cls
    return cls


def names() -> list[str]:
    return list(_LAUNCHERS)


def launcher_class(name: str, what: str = "--launcher") -> type[Launcher]:
    """The registered launcher ``name`` (or ``module:Class``, imported and registered: how a detached worker
    finds a launcher defined outside this package); one line naming the known ones when there is none."""
    if name in _LAUNCHERS:
        return _LAUNCHERS[name]
    module, _, attr = name.partition(":")
    if module and attr:
        try:
            return register(getattr(importlib.import_module(module), attr))
        except (ImportError, AttributeError) as exc:
            raise BronchoError(f"{what} {name}: cannot load it ({exc})") from None
    raise BronchoError(f"{what} {name}: must be one of {', '.join(_LAUNCHERS)}")


def reference(cls: type[Launcher]) -> str:
    """What a worker's spec names ``cls`` by: its name when this package registers it, else ``module:Class``."""
    return cls.name if cls.__module__.startswith(__name__ + ".") else f"{cls.__module__}:{cls.__qualname__}"


register(LocalLauncher)
register(SlurmLauncher)

__all__ = ["STAGE_ENV", "Launcher", "LocalLauncher", "SlurmLauncher", "Workers", "launcher_class", "names",
           "reference", "register"]
