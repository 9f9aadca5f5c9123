"""`bronchopose selftest`: prove training works on this machine's device (CUDA or CPU) in about a minute
(``diagnostics.entry.selftest``)."""

from __future__ import annotations

from typing import Optional

import typer

from .common import console


def selftest(
    device: str = typer.Option("auto", "--device", help="auto (CUDA when there is one), cpu or cuda."),
    precision: str = typer.Option("auto", "--precision", help="auto (bf16-mixed on CUDA with bf16, 16-mixed "
                                  "without, 32 on the CPU), 32, bf16-mixed or 16-mixed."),
    arch: Optional[list[str]] = typer.Option(None, "--arch", "-a", help="Architectures to train (repeatable; "
                                             "default: all five)."),
    threads: int = typer.Option(1, "--threads", min=1, help="torch CPU threads (the synthetic inputs are tiny: "
                                "one thread beats a team whose waits collide on a busy machine)."),
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
    """
    from ..diagnostics import entry  # lazy: torch loads only when the command runs

    raise typer.Exit(entry.selftest(device, precision, arch, threads=threads, console=console))
