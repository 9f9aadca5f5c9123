"""`bronchopose track`: apply a trained run's model to a folder of frames, a video or a dataset trajectory."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..api.arguments import DEFAULT_CONFIG
from .common import ConfigOpt, ProfileOpt, SetOpt, console


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
    from ..api import tools  # lazy: MLflow (~1 s) only once the command runs

    tools.track(input_path, run=run, model=model, best=best, first_pose=first_pose, ground_truth=ground_truth,
                out=out, register=register, progress=not quiet, config=config, profile=profile,
                overrides=set_ or (), console=console)
