"""`bronchopose profile`: parameters, GMACs, latency and peak memory per architecture (the ablation table)."""

from __future__ import annotations

import json
from typing import Annotated

import typer
from rich import box
from rich.table import Table

from ..errors import BronchoError
from .common import ShowFormat, console, err_console


def profile(
    arch: Annotated[
        list[str], typer.Option("--arch", "-a", help="Architecture to profile (repeatable), or 'all'.")
    ] = ["all"],  # noqa: B006 (typer copies the default)
    image_size: Annotated[int, typer.Option("--image-size", help="Square input size (paper: 256).")] = 256,
    device: Annotated[str, typer.Option("--device", help="cpu or cuda.")] = "cpu",
    batch: Annotated[int, typer.Option("--batch", help="Batch N for latency and memory.")] = 8,
    repeats: Annotated[int, typer.Option("--repeats", help="Timed forwards per figure (the median is reported).")] = 10,
    warmup: Annotated[int, typer.Option("--warmup", help="Untimed forwards before timing.")] = 2,
    window: Annotated[int, typer.Option("--window", help="Image pairs per forward (paper: 10).")] = 10,
    precision: Annotated[str, typer.Option("--precision", help="32, 16-mixed (cuda) or bf16-mixed (autocast).")] = "32",
    channels_last: Annotated[
        bool, typer.Option("--channels-last/--no-channels-last", help="Channels-last memory format.")
    ] = True,
    threads: Annotated[int | None, typer.Option("--threads", help="torch CPU threads.")] = None,
    fmt: Annotated[ShowFormat, typer.Option("--format", help="Output format.")] = "table",
) -> None:
    """Profile the architectures: parameters, GMAC per pair, latency per pair (batch 1 and N), peak memory.

    Each forward processes a window of --window pairs; latency is the median
    forward time divided by the pairs it processed. GMACs are counted with
    torch's FLOP counter (MAC = FLOP/2, LSTMs analytically) over one batch-1
    window. Peak memory is what one batch-N forward allocates above the resting
    model (CUDA: max_memory_allocated; CPU: peak bytes of live tensors).
    """
    if fmt not in ("table", "json"):
        raise BronchoError(f"--format {fmt!r}: must be table or json")
    from ..models import profile as profiling  # lazy: torch loads only when the command runs

    names = profiling.arch_names(arch)
    if threads is not None:
        profiling.set_threads(threads)
    kwargs = {"image_size": image_size, "device": device, "batch": batch, "repeats": repeats, "warmup": warmup,
              "window": window, "precision": precision, "channels_last": channels_last}
    rows = []
    for name in names:
        with err_console.status(f"profiling {name} at {image_size}x{image_size} on {device} ..."):
            rows.append(profiling.profile_arch(name, **kwargs))
    if fmt == "json":
        typer.echo(json.dumps(rows, indent=2))
        return
    table = Table(caption=profiling.caption(rows), box=box.SIMPLE_HEAD, pad_edge=False)
    for i, (_, title, _) in enumerate(profiling.COLUMNS):
        table.add_column(title, no_wrap=True, justify="left" if i == 0 else "right")
    for row in rows:
        table.add_row(*profiling.cells(row))
    console.print(table)
