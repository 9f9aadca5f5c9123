"""Options shared by several commands, and the console they print to."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console

from ..config import DEFAULT_CONFIG, Config, load_config

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


def load(config: Path = Path(DEFAULT_CONFIG), profile: str | None = None, overrides: list[str] | None = None) -> Config:
    return load_config(config, profile, overrides or ())
