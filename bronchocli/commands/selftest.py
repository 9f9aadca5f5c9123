"""`bronchopose selftest`: prove training works on this machine's device (CUDA or CPU) in about a minute
(``bronchocli.api.tools.selftest``)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG, RotLoss
from .common import ConfigOpt, ProfileOpt, SetOpt, console


def selftest(
    device: str = typer.Option("auto", "--device", help="auto (CUDA when there is one), cpu or cuda."),
    precision: str = typer.Option("auto", "--precision", help="auto (bf16-mixed on CUDA with bf16, 16-mixed "
                                  "without, 32 on the CPU), 32, bf16-mixed or 16-mixed."),
    arch: Optional[list[str]] = typer.Option(None, "--arch", "-a", help="Architectures to train (repeatable; "
                                             "default: all five)."),
    threads: Optional[int] = typer.Option(None, "--threads", min=1, help="torch CPU threads (default 1: the "
                                          "synthetic inputs are tiny, one thread beats a team whose waits collide "
                                          "on a busy machine; --learn: a fair share of the cores)."),
    learn: bool = typer.Option(False, "--learn", help="Instead: can --arch (default convlstm) learn on the "
                               "configured dataset? Memorise 30 of its training pairs and compare eval-mode with "
                               "batch-statistics loss; one line per architecture."),
    rot_loss: RotLoss = typer.Option("ce", "--rot-loss", "-l", help="With --learn: the rotation loss."),
    steps: int = typer.Option(100, "--steps", min=1, help="With --learn: optimiser steps of the memorisation."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Check this machine's training path: what it sees, each architecture training, resume, numerics, speed.

    Prints the environment (torch, CUDA, cuDNN, devices, free memory, bf16), then one
    row per check: a short training of every architecture on synthetic frames in the
    chosen precision (the loss must go down), a save -> resume across a different
    visible-device count (weights identical to an uninterrupted run), on CUDA the
    CUDA-vs-CPU agreement of every architecture (fp32 without TF32, and bf16), and a
    throughput line (engine pairs/s against the bare step). Exit code 0 when every
    check passed, 1 naming those that failed, 2 for a device this machine lacks.
    docs/training.md ("GPU") explains how to read it.

    With --learn it answers another question, on the configured dataset
    (--config, --profile, --set; generated first if missing): can this
    architecture learn here? Through the platform's own training path it
    memorises 30 training pairs and checks that evaluation (re-estimated
    BatchNorm) reproduces training (eval-mode ÷ batch-statistics loss); one line
    per architecture, exit code 1 when one cannot (docs/training.md, "Can it
    learn here?").
    """
    from ..api import tools  # lazy: torch loads only when the command runs

    if learn:
        raise typer.Exit(tools.learn(config, arch, rot_loss, steps=steps, threads=threads, profile=profile,
                                     overrides=set_ or (), console=console))

    raise typer.Exit(tools.selftest(device, precision, arch, threads=threads, console=console))
