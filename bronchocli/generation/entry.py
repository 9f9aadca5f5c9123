"""``bronchopose data generate`` as a library call: render the configured dataset into a folder (resumable) and
print what it holds."""

from __future__ import annotations

import json
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from .. import pathcheck
from ..config import Config
from ..errors import Interrupted


def summary(root: Path, seconds: float, already: bool) -> Table:
    """What ``dataset.json`` says the dataset holds (and how long rendering took)."""
    meta = json.loads((root / "dataset.json").read_text())
    counts = meta["counts"]
    table = Table.grid(padding=(0, 2))
    table.add_row("dataset", str(root) + ("  (already complete: nothing to do)" if already else ""))
    table.add_row("patients", ", ".join(meta["patients"]))
    table.add_row("lobes", ", ".join(meta["lobes"]))
    table.add_row("frames", f"{counts['frames']} in {counts['trajectories']} trajectories")
    table.add_row("image", "{}x{} px, {:.0f}° field of view".format(*meta["image_size"], meta["camera"]["fov_deg"]))
    table.add_row("camera positions", f"{counts['rejected_positions']} rejected proposals, "
                                      f"{counts['clamped_positions']} clamped towards the centreline")
    table.add_row("fingerprint", meta["fingerprint"][:16])
    if not already:
        table.add_row("time", f"{seconds:.1f} s")
    return table


def generate(cfg: Config, out: Path | None = None, *, workers: int | None = None, progress: bool = True,
             console: Console) -> Path:
    """Render the config's dataset into ``out`` (default: ``dataset.root``); returns the folder. A Ctrl-C keeps
    the frames rendered so far: the same call resumes."""
    from .pipeline import frames_on_disk, generate_dataset  # lazy: VTK loads only when generating

    root = pathcheck.resolve(out, "--out") if out is not None else cfg.paths.dataset
    pathcheck.check_output(root, "--out" if out is not None else "dataset.root")  # never /etc/..., one line
    already = (root / "dataset.json").is_file()
    start = time.perf_counter()
    try:
        generate_dataset(cfg, root=root, workers=workers, progress=progress)
    except KeyboardInterrupt:
        kept = frames_on_disk(root)[0] if root.is_dir() else 0
        if kept:
            raise Interrupted(f"data generate stopped; the {kept} frames rendered so far are kept in {root}: run "
                              "the same command again to resume") from None
        where = f"{root} holds no frame yet" if root.is_dir() else f"nothing was written ({root} was not created)"
        raise Interrupted(f"data generate stopped before the first frame; {where}: run the same command again to "
                          "start") from None
    console.print(summary(root, time.perf_counter() - start, already))
    return root
