"""`bronchopose ui`: the MLflow UI on 127.0.0.1 for the configured tracking store, opened on the runs table
(``bronchocli.api.tools.serve_ui``); another interface only with ``--expose``, which warns (MLflow's UI has no
authentication)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt, console, err_console


def ui(
    port: int = typer.Option(5000, "--port", help="Port to listen on."),
    host: str = typer.Option("127.0.0.1", "--host", help="Interface to listen on (127.0.0.1 keeps it local; any "
                             "other needs --expose)."),
    expose: bool = typer.Option(False, "--expose", help="Listen on a non-loopback --host although MLflow's UI has "
                                "no authentication (put it behind some: docs/training.md)."),
    allowed_host: Optional[list[str]] = typer.Option(None, "--allowed-host", help="Also answer requests naming "
                                                     "this host (a DNS alias, a reverse proxy's name); repeatable."),
    workers: Optional[int] = typer.Option(None, "--workers", "-w", min=1, help="Server worker processes "
                                          "(default: half the cores, 1 to 4)."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Start the MLflow UI for the config's tracking store and print the link to its runs table (Ctrl-C stops it).

    The link opens the config's experiment on the runs table of MLflow's model-training
    view: tick two or more runs and press Compare to see the params that differ (arch,
    seed, ...). Sweeps and Optuna studies are parent runs with their cells/trials nested.
    Filter with e.g. `params.arch = 'convlstm' and params.population = 'personalized'`.

    It listens on 127.0.0.1: MLflow's UI has no authentication. Another --host needs --expose
    (it prints a warning); see docs/training.md for putting it behind authentication. With --expose it
    answers requests naming this machine; --allowed-host NAME (repeatable) adds other names it is reached by.
    """
    from ..api import tools  # lazy: mlflow loads only when the UI starts

    tools.serve_ui(config, host=host, port=port, workers=workers, expose=expose, allowed=allowed_host or (),
                   warn=lambda line: err_console.print(line, markup=False, highlight=False, soft_wrap=True),
                   profile=profile, overrides=set_ or (), console=console)
