"""`bronchopose data generate`: render a synthetic bronchoscopy dataset (frames + poses) from airway anatomy
(``bronchocli.api.tools.generate``)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt, console


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
    from ..api import tools  # lazy: keeps `bronchopose --help` fast

    tools.generate(config, anatomy=anatomy, patients=patients, image_size=image_size, trajectories=trajectories,
                   seed=seed, out=out, workers=workers, progress=progress, profile=profile, overrides=set_ or (),
                   console=console)
