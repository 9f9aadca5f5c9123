"""`bronchopose profile`: parameters, GMACs, latency and peak memory per architecture (the ablation table;
``diagnostics.entry.profile``)."""

from __future__ import annotations

from typing import Annotated

import typer

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
    from ..diagnostics import entry  # lazy: torch loads only when the command runs

    entry.profile(arch, fmt=fmt, threads=threads, console=console, err_console=err_console, image_size=image_size,
                  device=device, batch=batch, repeats=repeats, warmup=warmup, window=window, precision=precision,
                  channels_last=channels_last)
