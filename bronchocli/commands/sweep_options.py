"""The options and the verb group that `bronchopose sweep`'s verbs share (commands/sweep.py, sweep_manage.py).

``bronchopose sweep`` with no verb (or with run's options only) is ``sweep run``. The launchers' options
(``--workers``, ``--gpus``, ``--per-gpu``, a plugin's own) are not declared here: ``launcher_flags`` adds them.
"""

from __future__ import annotations

from typing import Any

import typer
from typer._click import Context  # Typer 0.29 vendors click (pyproject pins typer < 0.30)
from typer.core import TyperGroup

from ..api.arguments import FIELDS
from .common import console as _console

ONLY_HELP = ("Run only matching cells: key=value[,value...], keys joined by ';' or repeated --only "
             f"({', '.join(FIELDS)}), e.g. --only 'arch=lstm,conv3d;population=personalized'.")
STORAGE_HELP = ("Claims database URL, overriding storage.url (sqlite:///runs/sweep.db; "
                "postgresql://user:${PGPASSWORD}@host/db for many machines).")
DEFAULT_VERB = "run"

class SweepGroup(TyperGroup):
    """A group whose default verb is ``run``: ``sweep [run's options]`` is ``sweep run [...]``."""

    def parse_args(self, ctx: Context, args: list[str]) -> list[str]:
        if not args or (args[0] not in self.commands and args[0] not in ctx.help_option_names):
            args = [DEFAULT_VERB, *args]
        return super().parse_args(ctx, args)


app = typer.Typer(cls=SweepGroup, no_args_is_help=False,
                  help="Run a sweep's plan exactly once per cell and manage it: run (the default), plan, status, "
                  "gc, cancel.")


def wide_console() -> Any:
    from ..api.manage import wide  # lazy: keeps `bronchopose --help` fast

    return wide(_console)


StorageOpt = typer.Option(None, "--storage", help=STORAGE_HELP)
OnlyOpt = typer.Option(None, "--only", help=ONLY_HELP)
UseTunedOpt = typer.Option(None, "--use-tuned", help="Apply the best trial of this Optuna study to every cell.")
