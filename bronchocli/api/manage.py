"""The sweep's management verbs and the config's check as calls: what ``bronchopose sweep plan | gc | cancel`` and
``bronchopose config`` do, each returning its exit code or what it shows.

As the work calls (``api.work``), each takes the config file with a ``profile`` and ``--set``-style
``overrides`` (``storage``: the claims database instead of ``storage.url``), checks it before anything is done
(one :class:`~bronchocli.errors.BronchoError` line), and prints only to the ``console`` it is given.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from rich.console import Console

from ..config import DEFAULT_CONFIG, Config, check_paths
from ..config.arguments import checked
from .work import config_of

if TYPE_CHECKING:
    from ..sweep.task import TaskSpec


def _silent() -> Console:
    return Console(quiet=True)


def _spec(config: str | os.PathLike, profile: str | None, overrides: Sequence[str], storage: str | None,
          use_tuned: str | None = None, only: Sequence[str] = ()) -> TaskSpec:
    """The config as the sweep's workers load it (``TaskSpec.load``: ``storage`` and ``use_tuned`` applied)."""
    from ..sweep.task import TaskSpec  # lazy: the sweep stack loads only when a sweep verb runs

    return TaskSpec(config=str(config), profile=profile, overrides=tuple(overrides), storage=storage,
                    use_tuned=use_tuned, only=tuple(only))


@checked
def plan(config: str | os.PathLike = DEFAULT_CONFIG, *, only: Sequence[str] = (), storage: str | None = None,
         use_tuned: str | None = None, profile: str | None = None, overrides: Sequence[str] = (),
         console: Console | None = None, **launcher_options: Any) -> int:
    """``sweep plan``: per stage its cells and their state, and the local workers a run would start, placed by the
    generic launcher options (``workers`` on ``gpus``, ``per_gpu`` each; no other is taken). Changes nothing
    anywhere. Returns the exit code (0)."""
    from ..sweep import entry  # lazy: the sweep stack loads only when a sweep verb runs

    spec = _spec(config, profile, overrides, storage, use_tuned, only)
    cfg = spec.load()
    return entry.dry_run(cfg, spec.selection(), options=launcher_options, console=console or _silent())


@checked
def gc(config: str | os.PathLike = DEFAULT_CONFIG, *, dry_run: bool = False, storage: str | None = None,
       profile: str | None = None, overrides: Sequence[str] = (), console: Console | None = None) -> int:
    """``sweep gc``: remove the checkpoints no live cell needs on this machine (``dry_run``: list them), then say
    what is kept and why. Returns the exit code (0)."""
    from ..sweep import entry  # lazy: the sweep stack loads only when a sweep verb runs

    cfg = _spec(config, profile, overrides, storage).load()
    return entry.gc(cfg, console or _silent(), dry_run=dry_run)


@checked
def cancel(config: str | os.PathLike = DEFAULT_CONFIG, *, launcher: str | None = None, dry_run: bool = False,
           study: str | None = None, storage: str | None = None, profile: str | None = None,
           overrides: Sequence[str] = (), console: Console | None = None) -> int:
    """``sweep cancel``: stop the sweep's (or tuning ``study``'s) queued and running workers of ``launcher``
    (default ``sweep.launcher``); ``dry_run``: list them. Returns the exit code."""
    from ..sweep import entry  # lazy: the sweep stack loads only when a sweep verb runs

    cfg = _spec(config, profile, overrides, storage).load()
    return entry.cancel(cfg, entry.launcher_kind(cfg, launcher), console or _silent(), dry_run=dry_run, study=study)


def check_config(config: str | os.PathLike | Config = DEFAULT_CONFIG, profile: str | None = None,
                 overrides: Sequence[str] = ()) -> Config:
    """``bronchopose config``'s check: the config loaded and validated, ``sweep.launcher`` a known launcher and every
    ``sweep.launchers`` section valid, and every path it names writable (what ``sweep`` checks before it starts);
    creates nothing, contacts no server."""
    from ..sweep.launchers import log_roots  # lazy: the launchers' registry only when the config is checked

    cfg = config_of(config, profile, overrides)
    check_paths(cfg, storage=True, logs=True, extra=log_roots(cfg))  # the config package cannot see the launchers
    return cfg


def grid(cfg: Config, console: Console) -> None:
    """``config --grid``: the plan's cells per stage (a selecting stage: what it will choose)."""
    from ..sweep import entry  # lazy: the sweep stack loads only when the grid is listed

    entry.grid(cfg, console)


def wide(console: Console) -> Any:
    """``console`` as wide as the sweep's tables need (its width where it has one, else wide enough)."""
    from ..sweep.status import wide as widened  # lazy: the sweep stack loads only when a sweep verb prints

    return widened(console)
