"""Options shared by several commands, and the console they print to."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Optional

import typer
from rich.console import Console

from .. import pathcheck
from ..config import DEFAULT_CONFIG, Config, load_config, parse_override

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


def load(config: Path = Path(DEFAULT_CONFIG), profile: str | None = None, overrides: list[str] | None = None) -> Config:
    return load_config(config, profile, overrides or ())


def load_or_defaults(config: Path, profile: str | None, overrides: list[str] | None, name: str) -> Config:
    """``load``, except that without an experiments.yaml (the default path missing, no profile) the defaults
    apply, named ``name``, with the overrides: commands that work on a dataset alone need no config file."""
    if config == Path(DEFAULT_CONFIG) and not config.exists() and not profile:
        return Config(name=name).with_values(dict(parse_override(s) for s in overrides or []))
    return load(config, profile, overrides)


def output_folder(path: Path, flag: str, kind: str = "folder") -> Path:
    """``path`` (``~`` expanded) checked as a ``folder`` (or a file) to write, by the one check every output goes
    through (``pathcheck.check_output``: no system folder, the right kind, creatable); creates nothing.

    BronchoError (one line) when it is a system folder, a file (a folder), lies under a file, or its nearest
    existing folder is not writable.
    """
    path = path.expanduser()
    pathcheck.check_output(path, flag, kind)
    return path
