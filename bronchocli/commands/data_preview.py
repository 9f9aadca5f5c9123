"""`bronchopose data preview`: a montage of sample frames and a 3-D plot of the camera positions of a dataset."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .. import pathcheck
from ..errors import BronchoError
from .common import console, output_folder


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
    from ..reporting.dataset_figures import preview as draw  # lazy: matplotlib only when drawing

    root = pathcheck.resolve(dataset, "--dataset")
    target = out if out is not None else Path("reports") / f"{root.name}-montage.png"
    if target.is_dir():
        raise BronchoError(f"--out {target}: is a folder; give the montage's file name, e.g. {target / 'montage.png'}")
    if target.suffix.lower() not in (".png", ".pdf"):
        target = target.with_suffix(".png")
    output_folder(target, "--out", "file")  # the montage file itself (its folder may be /tmp)
    formats = ["png", "pdf"] if pdf else [target.suffix.lstrip(".").lower()]
    for path in draw(root, target, columns=columns, formats=formats):
        console.print(f"wrote {path}")
