"""`bronchopose profile`: parameters, GMACs, latency and peak memory per architecture (the ablation table;
``bronchocli.api.tools.profile``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .common import ShowFormat, console, err_console


def profile(
    arch: Annotated[
        list[str], typer.Option("--arch", "-a", help="Architecture to profile (repeatable), or 'all'.")
    ] = ["all"],  # noqa: B006 (typer copies the default)
    image_size: Annotated[Optional[int], typer.Option("--image-size", help="Square input size (default: 256, "
                                                      "the paper's; --speed: 128).")] = None,
    device: Annotated[str, typer.Option("--device", help="cpu or cuda.")] = "cpu",
    full: Annotated[bool, typer.Option("--full/--quick", help="Full: batch N 8, 10 timed forwards after 2 warm-ups. "
                                       "Quick (default): batch N 2, 3 after 1 (the spread is in the JSON).")] = False,
    batch: Annotated[Optional[int], typer.Option("--batch", help="Batch N for latency and memory (--speed: "
                                                 "image pairs per training step, default 10).")] = None,
    repeats: Annotated[Optional[int], typer.Option("--repeats", help="Timed forwards per figure (the median is "
                                                   "reported).")] = None,
    warmup: Annotated[Optional[int], typer.Option("--warmup", help="Untimed forwards before timing.")] = None,
    window: Annotated[int, typer.Option("--window", help="Image pairs per forward (paper: 10).")] = 10,
    precision: Annotated[str, typer.Option("--precision", help="32, 16-mixed (cuda) or bf16-mixed (autocast).")] = "32",
    channels_last: Annotated[
        bool, typer.Option("--channels-last/--no-channels-last", help="Channels-last memory format.")
    ] = True,
    threads: Annotated[int | None, typer.Option("--threads", help="torch CPU threads.")] = None,
    fmt: Annotated[ShowFormat, typer.Option("--format", help="Output format.")] = "table",
    speed: Annotated[Optional[Path], typer.Option("--speed", help="Instead: measure training speed per setting "
                                                  "(fp32/bf16 x channels-last on/off) with a loss-curve check, "
                                                  "print a Markdown table and write the chosen per-architecture "
                                                  "settings for this device into this file (train.speed_settings).")
                      ] = None,
    steps: Annotated[int, typer.Option("--steps", help="--speed: training steps per setting (>= 50).")] = 50,
    backbone: Annotated[Optional[str], typer.Option("--backbone", help="--speed: the backbone of the BronchoPose "
                                                    "architectures (efficientnet_b0, the default, or "
                                                    "efficientnet_lite0).")] = None,
    frozen_stages: Annotated[int, typer.Option("--frozen-stages", min=0, max=8, help="--speed: measure the training "
                                               "on a cached frozen prefix of this many backbone stages "
                                               "(model.frozen_stages), its own entry in FILE; 0: the whole "
                                               "network.")] = 0,
) -> None:
    """Profile the architectures: parameters, GMAC per pair, latency per pair (batch 1 and N), peak memory.

    Each forward processes a window of --window pairs; latency is the median
    forward time divided by the pairs it processed. GMACs are counted with
    torch's FLOP counter (MAC = FLOP/2, LSTMs analytically) over one batch-1
    window. Peak memory is what one batch-N forward allocates above the resting
    model (CUDA: max_memory_allocated; CPU: peak bytes of live tensors).
    Quick by default (batch N 2, median of 3); --full for the paper table's settings.

    --speed FILE trains every architecture for --steps steps in each candidate
    setting, interleaved step by step, keeps those whose loss curve tracks fp32
    and writes the fastest per architecture for this device into FILE (the
    settings `train.precision: auto` / `model.channels_last: auto` use; the
    project ships the CPU's). docs/training.md, "Speed settings".
    """
    from ..api import tools  # lazy: torch loads only when the command runs

    tools.profile(arch, image_size=image_size, device=device, full=full, batch=batch, repeats=repeats, warmup=warmup,
                  window=window, precision=precision, channels_last=channels_last, threads=threads, fmt=fmt,
                  speed=speed, steps=steps, backbone=backbone, frozen_stages=frozen_stages, console=console,
                  err_console=err_console)
