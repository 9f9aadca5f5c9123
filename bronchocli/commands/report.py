"""`bronchopose report`: the paper's tables (Markdown + LaTeX) and figures from the config's MLflow runs."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

import typer

from ..api.arguments import DEFAULT_CONFIG, RULES, PoseFrame
from .common import ConfigOpt, ProfileOpt, SetOpt, console, err_console

Evaluation = Literal["accumulated", "pair", "both"]


def complete_tables(incomplete: str) -> list[str]:
    """Shell completion of --table: the registered tables (read when completing, not at start-up)."""
    from ..api.tools import table_names  # lazy: the reporting stack loads only when completing --table

    return [n for n in table_names() if n.startswith(incomplete)]


def report(
    table: str = typer.Option("all", "--table", "-t", help="personalized, cross-subject, sota, ablation, frames, "
                              "tracking or all.", autocompletion=complete_tables),
    evaluation: Evaluation = typer.Option("both", "--eval", "-e", help="Per pair, accumulated, or both."),
    fmt: Literal["md", "latex", "both"] = typer.Option("both", "--format", "-f", help="Markdown, LaTeX or both."),
    sweep: Optional[str] = typer.Option(None, "--sweep", help="Report a stored sweep by name (tag `sweep`): all its "
                                        "cell runs, not tied to the config's cells. Default: the config's cells."),
    include_other_configs: bool = typer.Option(False, "--include-other-configs", help="Also use runs of the "
                                               "config's sweep made under another config (other cell keys)."),
    out: Path = typer.Option(Path("reports"), "--out", "-o", help="Output directory."),
    pose_frame: Optional[PoseFrame] = typer.Option(None, "--pose-frame", help="The main tables' pose frame; "
                                                   "default: the runs' only one, else world (the frames table "
                                                   "compares both)."),
    best: int = typer.Option(0, "--best", **RULES["best"].bounds(), help="Cross-subject tables: keep the best "
                             "N network/loss combinations by mean rank over the metrics (the paper shows 3); 0: all."),
    figures: Optional[bool] = typer.Option(None, "--figures/--no-figures", help="Figures (default: with -t all only)."),
    trajectories: int = typer.Option(4, "--trajectories", **RULES["trajectories"].bounds(), help="Test "
                                     "trajectories in the trajectory figure."),
    latency: bool = typer.Option(True, "--latency/--no-latency", help="Ablation: measure latency/GMAC with "
                                 "`bronchopose profile` (without: those columns stay empty)."),
    latency_from: Optional[Path] = typer.Option(None, "--latency-from", help="Ablation: read latency/GMAC from "
                                                "`bronchopose profile --format json` output instead of measuring."),
    latency_device: str = typer.Option("cpu", "--latency-device", help="Ablation profiling device: cpu or cuda."),
    image_size: Optional[int] = typer.Option(None, "--image-size", help="Ablation profiling input size "
                                             "(default: data.image_size or dataset.generate.image_size)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Do not print the tables nor the progress lines."),
    to_parent: bool = typer.Option(True, "--log-to-parent/--no-log-to-parent", help="Also log the written files "
                                   "to the sweep's parent MLflow run (artifacts report/), to read them in the UI."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Build the paper's tables and figures from the FINISHED runs of the config's cells; write them to --out.

    Tables: personalized (Tables 2 accumulated / 3 per pair), cross-subject
    (Tables 4/5), sota (Table 6, BronchoTrack vs OffsetNet), ablation (params,
    latency, GMAC, position L2, CE per architecture), frames (skill with
    world vs camera labels, when the runs have both) and tracking (CTF, ATE,
    RPE, drift per network/loss). Cells are "mean [95% interval]" over seeds
    (t interval on variance components over seeds and test trajectories);
    bold = significantly best of its column (paired t test, Holm, alpha 0.05),
    bold≈ = tied for best, † = no better than an image-blind reference (the
    "Zero motion" and "Training mean" rows), ‡ = the model ignores its input. Only runs whose cell_key is a cell of the
    config count (--sweep NAME: a stored sweep without the config). Figures
    (PNG + PDF): trajectories, error vs frame, skill per table, the learning
    curve (several train_trajectories), dataset frames and positions. The
    written files are also logged to the sweep's parent MLflow run (artifacts
    report/). See docs/reports.md.
    """
    from .. import api  # lazy: keeps `bronchopose --help` fast

    api.report(config, table=table, evaluation=evaluation, fmt=fmt, out=out, sweep=sweep, pose_frame=pose_frame,
               include_other_configs=include_other_configs, best=best, figures=figures, trajectories=trajectories,
               latency=latency, latency_from=latency_from, latency_device=latency_device, image_size=image_size,
               to_parent=to_parent, profile=profile, overrides=set_ or (), console=console,
               err_console=err_console, quiet=quiet)
