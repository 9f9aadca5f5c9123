"""`bronchopose data stats`: counts, lengths and pose ranges of a dataset, and of one population's split
(``bronchocli.api.tools.data_stats``)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG, Population
from .common import ConfigOpt, ProfileOpt, SetOpt, console


def stats(
    dataset: Optional[Path] = typer.Argument(None, metavar="DATASET",
                                             help="Dataset directory (default: the config's dataset.root)."),
    population: Optional[Population] = typer.Option(None, "--population", help="Also show the split of this "
                                                    "population."),
    fold: Optional[str] = typer.Option(None, "--fold", help="Held-out patient (cross-subject)."),
    manifest: Optional[Path] = typer.Option(None, "--manifest", help="Write the split manifest CSV here "
                                            "(patient, lobe, trajectory, split); needs --population."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Summarise a dataset: trajectories and frames per patient and lobe, trajectory lengths, pose ranges,
    image size and fingerprint, and the trajectories whose world-frame labels pass near gimbal lock.
    With --population (and --fold for cross-subject), also the per-split counts
    of that population under the config's `splits`, and with --manifest the split manifest as CSV.

    The dataset is read as the config's dataset.format (bronchopose, or csv with dataset.csv's mapping).
    """
    from ..api import tools  # lazy: pandas only when the command runs (keeps --help fast)

    tools.data_stats(config, dataset=dataset, population=population, fold=fold, manifest=manifest, profile=profile,
                     overrides=set_ or (), console=console)
