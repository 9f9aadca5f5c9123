"""Options shared by several commands, and the console they print to. Like every command module it imports only
Typer, Rich and ``bronchocli.api`` (``tests/test_architecture.py``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Optional

import typer
from rich.console import Console

console = Console()
err_console = Console(stderr=True)

ConfigOpt = Annotated[
    Path, typer.Option("--config", "-c", help="Experiment config (YAML).", show_default=True)
]
ProfileOpt = Annotated[
    Optional[str], typer.Option("--profile", "-p", help="Named profile from the config's `profiles` (e.g. paper).")
]
SetOpt = Annotated[
    Optional[list[str]],
    typer.Option("--set", "-s", help="Override a config value: key.path=value (repeatable), e.g. train.lr=3e-4."),
]


ShowFormat = Literal["table", "json"]  # choices are Literal types: --help lists them, the shell completes them
