"""`bronchopose data stats`: counts, lengths and pose ranges of a dataset, and of one population's split."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from ..cells import Population
from ..config import DEFAULT_CONFIG, Config, parse_override
from ..errors import ConfigError
from .common import ConfigOpt, ProfileOpt, SetOpt, console, load


def _config(config: Path, profile: str | None, set_: list[str] | None, dataset: Path | None) -> Config:
    # Inspecting a dataset should not need an experiments.yaml: without one, the defaults apply.
    if dataset is not None and config == Path(DEFAULT_CONFIG) and not config.exists() and not profile:
        cfg = Config(name="data-stats").with_values(dict(parse_override(s) for s in set_ or []))
    else:
        cfg = load(config, profile, set_)
    return cfg.with_values({"dataset.root": str(dataset.expanduser().resolve())}) if dataset is not None else cfg


def _table(df, title: str) -> Table:
    table = Table(*map(str, df.columns), title=title)
    for row in df.itertuples(index=False):
        table.add_row(*(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row))
    return table


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
    image size and fingerprint, and the trajectories whose world-frame labels pass near gimbal lock. With --population (and --fold for cross-subject), also the per-split counts
    of that population under the config's `splits`, and with --manifest the split manifest as CSV.

    The dataset is read as the config's dataset.format (bronchopose, or csv with dataset.csv's mapping).
    """
    from ..data import stats as st  # lazy: pandas only when the command runs (keeps --help fast)
    from ..data.source import open_dataset
    from ..data.splits import make_split

    if manifest is not None and population is None:
        raise ConfigError("--manifest needs --population (personalized or cross-subject)")
    cfg = _config(config, profile, set_, dataset)
    ds = open_dataset(cfg)
    facts = Table.grid(padding=(0, 2))
    for k, v in st.overview(ds).items():
        facts.add_row(k, v)
    console.print(facts)
    console.print(_table(st.per_lobe(ds), "per patient and lobe (lengths in frames)"))
    console.print(_table(st.pose_ranges(ds), "pose ranges (voxels, degrees)"))
    gimbal = st.gimbal_table(ds)
    if len(gimbal):
        console.print(_table(gimbal, "world-frame labels near gimbal lock: Euler differences far larger than "
                                     "the rotation between frames (pose_frame world is not the motion there; "
                                     "camera-frame labels are unaffected, docs/conventions.md)"))
    if population is None:
        return
    split = make_split(ds, population, fold, cfg.splits)
    title = f"{population}" + (f", test patient {fold}" if fold else "")
    console.print(_table(st.split_counts(split, cfg.data.window, cfg.data.overlap), f"split: {title}"))
    console.print(_table(st.split_per_patient(split, ds), "trajectories per patient and lobe"))
    for note in split.notes:
        console.print(f"note: {note}", markup=False, highlight=False)
    if manifest is not None:
        path = split.write_manifest(manifest)
        console.print(f"manifest written to {path}", markup=False, highlight=False)
