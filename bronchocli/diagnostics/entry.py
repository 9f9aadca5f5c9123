"""``bronchopose profile`` and ``bronchopose selftest`` as library calls: measure the architectures, or prove
this machine's training path, and print the tables."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from rich import box
from rich.console import Console
from rich.table import Table

from ..config import Config, check_paths
from ..errors import BronchoError
from ..generation import ensure_dataset
from ..models import ARCHITECTURES, EFFICIENT_BACKBONES, PAPER_BACKBONE, EfficientPairNet
from ..models import profile as profiling
from ..runs import cores
from . import learning
from . import selftest as st
from . import speed as sp


@contextmanager
def cpu_share(threads: int | None) -> Iterator[int]:
    """The torch CPU threads of a command that trains or times models: ``--threads`` when given, else its share
    of the cores beside the project's other processes (``runs.cores``), claimed while the block runs."""
    with cores.CoreShare(threads, explicit_from="--threads") as share:
        profiling.set_threads(share.check().threads)
        yield share.threads


def profile(archs: Sequence[str], *, fmt: str = "table", threads: int | None = None, console: Console,
            err_console: Console, **kwargs: Any) -> None:
    """Parameters, GMAC, latency and peak memory of ``archs`` (or ``all``), one row each, as a table or JSON;
    ``kwargs`` are ``profile_arch``'s (image_size, device, batch, repeats, warmup, window, precision,
    channels_last)."""
    names = profiling.arch_names(archs)
    with cpu_share(threads):
        rows = _profile_rows(names, err_console, **kwargs)
    if fmt == "json":
        console.file.write(json.dumps(rows, indent=2) + "\n")  # verbatim: no markup, wrapping or emoji codes
        return
    table = Table(caption=profiling.caption(rows), box=box.SIMPLE_HEAD, pad_edge=False)
    for i, (_, title, _) in enumerate(profiling.COLUMNS):
        table.add_column(title, no_wrap=True, justify="left" if i == 0 else "right")
    for row in rows:
        table.add_row(*profiling.cells(row))
    console.print(table)


def _profile_rows(names: Sequence[str], err_console: Console, **kwargs: Any) -> list[dict[str, Any]]:
    rows = []
    started = time.perf_counter()
    for i, name in enumerate(names, 1):
        with err_console.status(f"[{i}/{len(names)}] profiling {name} at {kwargs['image_size']}x"
                                f"{kwargs['image_size']} on {kwargs['device']} ..."):
            rows.append(profiling.profile_arch(name, **kwargs))
        r = rows[-1]
        err_console.print(f"[{i}/{len(names)}] {name}: {r['latency_ms_b1']:.2f} ms/pair at batch 1 (spread "
                          f"{r['latency_spread_b1']:.0%}), {time.perf_counter() - started:.0f} s so far", highlight=False)
    return rows


def selftest(device: str = "auto", precision: str = "auto", archs: Sequence[str] | None = None, *,
             threads: int | None = 1, console: Console) -> int:
    """``_selftest`` holding its claim on the cores (``cpu_share``: ``--threads``, else a share) while it runs."""
    with cpu_share(threads):
        return _selftest(device, precision, archs, console=console)


def _selftest(device: str, precision: str, archs: Sequence[str] | None, *, console: Console) -> int:
    """The environment, then every check (train each architecture, resume, CUDA vs CPU, throughput); exit code
    0 when all passed, 1 when some failed."""
    unknown = [a for a in archs or [] if a not in ARCHITECTURES]
    if unknown:
        raise BronchoError(f"--arch {', '.join(unknown)}: unknown (valid: {', '.join(ARCHITECTURES)})")
    dev = st.resolve_device(device)
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
        checks = st.run(dev, prec, archs, on_check=seen)
    for c in checks:
        table.add_row(c.name, "[green]ok[/]" if c.ok else "[bold red]FAILED[/]", f"{c.seconds:.1f}", c.detail)
    console.print(table)
    failed = [c.name for c in checks if not c.ok]
    if failed:
        console.print(f"[bold red]selftest failed:[/] {', '.join(failed)}")
        return 1
    console.print(f"[green]selftest passed:[/] {len(checks)} checks on {dev} in {prec}")
    return 0


def speed(archs: Sequence[str], out: Path, *, device: str, image_size: int, pairs: int, steps: int,
          threads: int | None, console: Console, err_console: Console, backbone: str | None = None,
          frozen_stages: int = 0) -> None:
    """``profile --speed``: measure the speed settings of ``archs`` on ``device``, print the Markdown table and
    write them into ``out`` (diagnostics/speed.py). ``frozen_stages``: the training on a cached prefix of that many
    stages of ``backbone`` (the paper's when None), for the architectures whose backbones have stages; one named
    that has none is refused, ``all`` leaves it out."""
    backbone = backbone or PAPER_BACKBONE
    if backbone not in EFFICIENT_BACKBONES:
        raise BronchoError(f"--backbone {backbone}: not one of {', '.join(EFFICIENT_BACKBONES)}")
    names = profiling.arch_names(archs)
    if frozen_stages:
        stageless = [a for a in names if not issubclass(ARCHITECTURES[a], EfficientPairNet)]
        if stageless and "all" not in archs:
            raise BronchoError(f"--frozen-stages {frozen_stages}: {', '.join(stageless)} has no backbone stages to "
                               "freeze (its own backbones); measure it without --frozen-stages")
        names = [a for a in names if a not in stageless]
    dev = profiling.resolve_device(device)
    out = Path(out)
    if out.is_dir():
        raise BronchoError(f"--speed {out}: is a folder; give the settings file's path")
    started = time.perf_counter()
    with cpu_share(threads), err_console.status("measuring ...") as status:
        def progress(text: str) -> None:
            line = f"[{time.perf_counter() - started:.0f} s] {text}"
            status.update(line)
            err_console.print(line, highlight=False)
        table = sp.run(names, dev, out, image_size=image_size, pairs=pairs, steps=steps, progress=progress,
                       backbone=backbone, frozen=frozen_stages)
    console.file.write(table + "\n")  # verbatim Markdown
    console.print(f"wrote {out} ({time.perf_counter() - started:.0f} s)", highlight=False)


def learn(cfg: Config, archs: Sequence[str], rot_loss: str, *, steps: int, threads: int | None, console: Console) -> int:
    """``selftest --learn``: for each architecture, can it memorise a handful of the configured dataset's pairs,
    and does its evaluation agree with its training (``learning.check``)? One line each; exit 1 when one cannot."""
    unknown = [a for a in archs if a not in ARCHITECTURES]
    if unknown:
        raise BronchoError(f"--arch {', '.join(unknown)}: unknown (valid: {', '.join(ARCHITECTURES)})")
    check_paths(cfg)
    ensure_dataset(cfg)
    failed = 0
    with cpu_share(threads):
        for arch in archs:
            cell = cfg.cell(arch=arch, rot_loss=rot_loss, population="personalized", seed=0)
            with console.status(f"{arch}: memorising {learning.PAIRS} training pairs for {steps} steps ..."):
                verdict = learning.check(cfg, cell, steps=steps)
            colour = "green" if verdict.ok else "bold red"
            console.print(f"[{colour}]{verdict.line()}[/]", highlight=False)
            failed += not verdict.ok
    return 1 if failed else 0
