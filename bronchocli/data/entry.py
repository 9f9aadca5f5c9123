"""``bronchopose data stats`` as a library call: a dataset's counts, lengths and pose ranges, and optionally one
population's split (with its manifest CSV)."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console
from rich.table import Table

from ..config import Config
from . import stats as st
from .source import open_dataset
from .splits import make_split


def _table(df, title: str) -> Table:
    table = Table(*map(str, df.columns), title=title)
    for row in df.itertuples(index=False):
        table.add_row(*(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row))
    return table


def stats(cfg: Config, *, population: str | None = None, fold: str | None = None, manifest: Path | None = None,
          console: Console) -> None:
    """Print the config's dataset (read as ``dataset.format``); with ``population`` also its split under the
    config's ``splits`` (``fold``: the held-out patient), written to ``manifest`` when given."""
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
