"""`bronchopose data preview`: a montage of sample frames and a 3-D plot of the camera positions of a dataset."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .common import console


def preview(
    dataset: Path = typer.Argument(..., help="Dataset folder (the one holding dataset.json)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Montage image; the positions plot is written "
                                       "beside it as <stem>-positions. Default: reports/<dataset>-montage.png."),
    columns: int = typer.Option(6, "--columns", min=1, help="Frames per (patient, lobe) row of the montage."),
    pdf: bool = typer.Option(False, "--pdf", help="Also write PDF versions of both figures."),
) -> None:
    """Draw a dataset: a PNG montage of frames sampled along one trajectory per patient and lobe, and a
    3-D plot of every camera position visited per patient (voxel axes, coloured by lobe, over the centreline).
    """
    from ..api import tools  # lazy: matplotlib only when drawing

    for path in tools.preview(dataset, out=out, columns=columns, pdf=pdf):
        console.print(f"wrote {path}")
