"""`bronchopose status`: per-cell state of a sweep, its MLflow runs and headline metrics."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt
from .common import console as _console


def status(
    sweep: Optional[str] = typer.Option(None, "--sweep", help="Sweep name (default: the config's name)."),
    show_all: bool = typer.Option(False, "--all",
                                  help="Every stored cell of the sweep, also those of earlier configs."),
    storage: Optional[str] = typer.Option(None, "--storage", help="Claims database URL, overriding storage.url."),
    repair: bool = typer.Option(False, "--repair", help="First end the runs left RUNNING by a process that died "
                                "(FAILED) or by a sweep worker that lost its claim (KILLED) and the parent run of a "
                                "detached sweep whose workers all went before any ran, and make pending again the "
                                "claims rows that are damaged or whose run MLflow does not have. Without it, status "
                                "writes nothing."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Show each cell of a sweep: state, attempts, MLflow run id, duration, pair and accumulated position L2.

    Cells are those of the config's grid (a changed config means new cells); `--all`
    or another `--sweep` name lists every stored cell instead. Failed cells are listed
    with their reason. The checkpoint column and line show the disk each cell's
    resumable state takes on this machine, and how much no live cell needs
    (`bronchopose sweep gc` frees it).
    """
    from .. import api  # lazy: keeps `bronchopose --help` fast
    from ..api import manage

    api.status(config, sweep=sweep, show_all=show_all, repair=repair, storage=storage, profile=profile,
               overrides=set_ or (), console=manage.wide(_console))
