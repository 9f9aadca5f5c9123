"""`bronchopose data ...`: the dataset command group (generate, preview, stats)."""

from __future__ import annotations

import typer

from . import data_generate, data_preview, data_stats

app = typer.Typer(help="Generate, inspect and summarise datasets.", no_args_is_help=True)

# Subcommands are registered by their modules below (one explicit line each).
app.command(name="generate")(data_generate.generate)
app.command(name="preview")(data_preview.preview)
app.command(name="stats")(data_stats.stats)
