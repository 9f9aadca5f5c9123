"""`bronchopose track`: apply a trained run's model to a folder of frames, a video or a dataset trajectory."""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from ..config import DEFAULT_CONFIG
from ..errors import BronchoError
from .common import ConfigOpt, ProfileOpt, SetOpt, console, load, output_folder

METRIC_UNITS = {"pos_l2": "vox", "pos_l2_mm": "mm", "rot_l2": "deg", "de": "rad", "ce": "", "geodesic": "deg"}
SOURCES = ("model", "zero_motion", "train_mean")


def _errors_table(errors) -> Table:
    """Per metric and evaluation (per pair: mean over pairs; accumulated: endpoint error), model vs references."""
    row = errors.iloc[0]
    table = Table(title="errors: per pair (mean) and accumulated (endpoint after chaining)")
    for name in ("metric", "evaluation", *SOURCES):
        table.add_column(name.replace("_", " "), justify="left" if name in ("metric", "evaluation") else "right")
    for metric, unit in METRIC_UNITS.items():
        if f"model.pair.{metric}" not in row:
            continue
        for ev, text in (("pair", "per pair"), ("acc", "accumulated")):
            values = [float(row[f"{s}.{ev}.{metric}"]) for s in SOURCES]
            table.add_row(f"{metric} ({unit})" if unit else metric, text,
                          *("nan" if math.isnan(v) else f"{v:.6g}" for v in values))
    return table


def track(
    input_path: Path = typer.Argument(..., metavar="INPUT", help="A folder of frames, a video file, or "
                                      "<dataset root>/<patient>/<lobe>/<trajectory>."),
    run: Optional[str] = typer.Option(None, "--run", help="MLflow run id whose model to apply."),
    model: Optional[str] = typer.Option(None, "--model", help="MLflow model URI: models:/NAME/VERSION, "
                                        "models:/NAME@ALIAS, models:/MODEL_ID, runs:/RUN_ID/model or a local folder."),
    best: Optional[str] = typer.Option(None, "--best", help="Apply the best run of this report table "
                                       "(personalized or cross-subject) by the headline figure."),
    first_pose: Optional[str] = typer.Option(None, "--first-pose", help="Pose of the first frame x,y,z,rx,ry,rz "
                                             "(voxels, degrees); default: the ground truth's, else all zeros."),
    ground_truth: Optional[Path] = typer.Option(None, "--ground-truth", help="Poses to score against (a pose CSV, "
                                                "or <dataset root>/<patient>/<lobe>/<trajectory>)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output folder (default: track/<input name>, "
                                       "track/<patient>-<lobe>-<trajectory> for a dataset trajectory)."),
    register: Optional[str] = typer.Option(None, "--register", help="Also register the model in the MLflow Model "
                                           "Registry under this name (a new version)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Track the camera through new frames with a trained model: trajectory CSV, 3-D plot, errors.

    The model is a run's MLflow Model (`--run`), any MLflow model URI (`--model`), or the
    best run of a report table (`--best personalized`). Writes `trajectory.csv` (one row per
    frame: pos_x pos_y pos_z Rx Ry Rz as in a dataset CSV, plus the relative pose d_*) and
    `trajectory.png`; with ground truth (a dataset trajectory, or `--ground-truth`) also
    `errors.csv` and a table of per-pair and accumulated errors next to both image-blind
    references. Frames of another size than the model's are resized with a warning.
    """
    from ..inference import loading, reader, trajectory  # lazy: MLflow (~1 s) only once the flags are valid
    from ..runs.client import client_for

    chosen = [f for f, v in (("--run", run), ("--model", model), ("--best", best)) if v]
    if len(chosen) != 1:
        raise BronchoError(f"give exactly one of --run, --model, --best (got {', '.join(chosen) or 'none'})")
    first = trajectory.parse_pose(first_pose) if first_pose is not None else None
    inp = reader.open_input(input_path)
    name = "-".join(input_path.parts[-3:]) if inp.kind == "trajectory" else (input_path.stem or "input")
    out = output_folder(out or Path("track") / name, "--out")
    truth = reader.read_ground_truth(ground_truth) if ground_truth is not None else None
    cfg = load(config, profile, set_)
    client = client_for(cfg)
    if best:
        from ..reporting.best import best_run  # lazy: the report's run collection only for --best

        chosen_best = best_run(client, cfg, best)
        console.print(chosen_best.describe())
        run = chosen_best.run.run_id
    loaded = loading.load(client, run or model)
    if register:
        version = loading.register(client, loaded.ref, register)
        console.print(f"registered as models:/{register}/{version}")
    spec = loaded.model.spec
    console.print(f"[bold]track[/] {inp.name} ({inp.kind}, {inp.n_frames or '?'} frames, {inp.shape[1]}x"
                  f"{inp.shape[0]}) with {loaded.label} (run {loaded.ref.run_id or '?'}, {spec['pose_frame']} "
                  f"pose frame, {spec['image_size']} px)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = trajectory.track(loaded.model, inp, first, truth, progress=not quiet)
    for w in caught:
        console.print(f"[yellow]warning:[/] {w.message}")
    title = result.truth.key if result.truth is not None and result.truth.key else Path(inp.name).name
    files = trajectory.write(result, out, title=title, model_label=loaded.label)
    console.print(f"{len(result.poses)} poses chained in the {result.pose_frame} frame from "
                  f"({', '.join(f'{v:g}' for v in result.first_pose)})")
    if result.errors is not None:
        console.print(_errors_table(result.errors))
    for f in files:
        console.print(f"wrote {f}")
