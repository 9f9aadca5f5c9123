"""`bronchopose sweep run | plan | status | gc | cancel`: a sweep's verbs, each with only its own options.

``run`` in ``sweep_run`` (``bronchocli.api.sweep``); ``plan``, ``gc`` and ``cancel`` in ``sweep_manage``; the
shared options and the verb group (``sweep`` alone is ``sweep run``; the old mode flags are refused) in
``sweep_options``; docs/sweep.md, "Verbs". Registered here, in the order ``--help`` lists them; ``run`` and
``plan`` with the launchers' options as flags (``launcher_flags``).
"""

from __future__ import annotations

from . import status as status_cmd
from .launcher_flags import command
from .sweep_manage import cancel, gc, plan
from .sweep_options import app
from .sweep_run import run

app.command(name="run", cls=command())(run)  # every installed launcher's options
app.command(name="plan", cls=command(generic_only=True))(plan)  # the local workers a run would start
app.command(name="gc")(gc)
app.command(name="cancel")(cancel)
app.command(name="status")(status_cmd.status)  # the same command as `bronchopose status`

__all__ = ["app"]
