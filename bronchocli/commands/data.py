"""`bronchopose data ...`: the dataset command group (generate, preview, stats)."""

from __future__ import annotations

import typer

app = typer.Typer(help="Generate, inspect and summarise datasets.", no_args_is_help=True)

# Subcommands are registered by their modules below (one explicit line each).
