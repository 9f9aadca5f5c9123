"""`bronchopose selftest`: prove training works on this machine's device (CUDA or CPU) in about a minute."""

from __future__ import annotations

from typing import Optional

import typer
from rich import box
from rich.table import Table

from ..errors import BronchoError
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
    from ..diagnostics import selftest as st  # lazy: torch loads only when the command runs
    from ..models import ARCHITECTURES  # lazy: torch loads only when the command runs

    unknown = [a for a in arch or [] if a not in ARCHITECTURES]
    if unknown:
        raise BronchoError(f"--arch {', '.join(unknown)}: unknown (valid: {', '.join(ARCHITECTURES)})")
    dev = st.resolve_device(device)
    st.torch.set_num_threads(threads)
    prec = st.resolve_precision(precision, dev)
    env = Table(title="selftest: what this machine offers", box=box.SIMPLE_HEAD, show_header=False)
    for what, value in st.environment(dev, prec):
        env.add_row(what, value)
    console.print(env)
    table = Table(title=f"selftest on {dev} in {prec}", box=box.SIMPLE_HEAD)
    for title in ("check", "result", "s", "detail"):
        table.add_column(title, no_wrap=title != "detail", justify="right" if title == "s" else "left")
    with console.status("running the checks ...") as status:
        def seen(check: st.Check) -> None:
            status.update(f"{check.name}: {'ok' if check.ok else 'FAILED'}; running the next check ...")
        checks = st.run(dev, prec, arch, on_check=seen)
    for c in checks:
        table.add_row(c.name, "[green]ok[/]" if c.ok else "[bold red]FAILED[/]", f"{c.seconds:.1f}", c.detail)
    console.print(table)
    failed = [c.name for c in checks if not c.ok]
    if failed:
        console.print(f"[bold red]selftest failed:[/] {', '.join(failed)}")
        raise typer.Exit(1)
    console.print(f"[green]selftest passed:[/] {len(checks)} checks on {dev} in {prec}")
