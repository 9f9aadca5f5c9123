"""`bronchopose data generate`: render a synthetic bronchoscopy dataset (frames + poses) from airway anatomy."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from ..config import DEFAULT_CONFIG, Config, parse_override
from ..errors import BronchoError, Interrupted
from ..extras import require
from .common import ConfigOpt, ProfileOpt, SetOpt, console, load


def _config(config: Path, profile: str | None, set_: list[str] | None) -> Config:
    # Flags alone are enough: without an experiments.yaml the defaults apply.
    if config == Path(DEFAULT_CONFIG) and not config.exists() and not profile:
        return Config(name="data-generate").with_values(dict(parse_override(s) for s in set_ or []))
    return load(config, profile, set_)


def _flag_overrides(anatomy: str | None, **flags) -> list[str]:
    """The flags as ``--set`` overrides, so a bad value is reported like any other override."""
    values = {k: v for k, v in flags.items() if v is not None}
    if anatomy is not None:
        # A path on the command line is relative to the working directory, not to the config file.
        values["anatomy"] = anatomy if anatomy == "procedural" else str(Path(anatomy).expanduser().resolve())
    return [f"dataset.generate.{k}={json.dumps(v)}" for k, v in values.items()]


def _summary(root: Path, seconds: float, already: bool) -> Table:
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


def generate(
    anatomy: Optional[str] = typer.Option(None, "--anatomy", help="'procedural' or an anatomy file "
                                          "(.vtu/.vtp graph, .nii/.nii.gz/.mhd/.nrrd volume, .stl/.obj/.vtp mesh)."),
    patients: Optional[int] = typer.Option(None, "--patients", help="Procedural patients (seeds seed, seed+1, ...)."),
    image_size: Optional[int] = typer.Option(None, "--image-size", help="Frame width and height in pixels."),
    trajectories: Optional[int] = typer.Option(None, "--trajectories", help="Trajectories per patient and lobe."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Base seed of anatomies and trajectories."),
    out: Optional[Path] = typer.Option(None, "--out", help="Dataset folder (default: the config's dataset.root)."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Rendering processes "
                                          "(default: dataset.generate.workers); the output does not depend on it."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show the progress bar."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Render a synthetic bronchoscopy dataset: frames (PNG) and camera poses (CSV per patient) along the
    four lobe paths of each airway, as configured in dataset.generate of experiments.yaml; the flags override it.

    Resumable: run it again after an interruption and it continues where it stopped (same seed, same bytes).
    A folder holding a dataset of a different config is refused. See docs/generator.md.
    """
    require("render", "data generate", ("vtkmodules",))
    from ..generation.pipeline import generate_dataset  # lazy: VTK loads only when generating

    flags = _flag_overrides(anatomy, patients=patients, image_size=image_size, trajectories=trajectories, seed=seed)
    cfg = _config(config, profile, [*(set_ or []), *flags])
    root = out.expanduser().resolve() if out is not None else cfg.paths.dataset
    if root.exists() and not root.is_dir():
        raise BronchoError(f"--out {root}: is a file, not a dataset folder; choose a folder path")
    already = (root / "dataset.json").is_file()
    start = time.perf_counter()
    try:
        generate_dataset(cfg, root=root, workers=workers, progress=progress)
    except KeyboardInterrupt:
        raise Interrupted(f"data generate stopped; the frames rendered so far are kept in {root}: run the same "
                          "command again to resume") from None
    console.print(_summary(root, time.perf_counter() - start, already))
