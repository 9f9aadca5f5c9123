"""`bronchopose report`: the paper's tables (Markdown + LaTeX) and figures from a sweep's MLflow runs."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..cells import POSE_FRAMES
from ..config import DEFAULT_CONFIG
from ..errors import BronchoError
from .common import ConfigOpt, ProfileOpt, SetOpt, console, err_console, load


def report(
    table: str = typer.Option("all", "--table", "-t", help="personalized, cross-subject, sota, ablation or all."),
    evaluation: str = typer.Option("both", "--eval", "-e", help="accumulated, pair or both."),
    fmt: str = typer.Option("both", "--format", "-f", help="md, latex or both."),
    sweep: Optional[str] = typer.Option(None, "--sweep", help="Sweep name (tag `sweep`); default: the config's name."),
    out: Path = typer.Option(Path("reports"), "--out", "-o", help="Output directory."),
    pose_frame: Optional[str] = typer.Option(None, "--pose-frame", help=f"Only runs in this pose frame "
                                             f"({', '.join(POSE_FRAMES)}); needed when the sweep mixes them."),
    best: int = typer.Option(0, "--best", help="Cross-subject tables: keep the best N network/loss combinations "
                             "by mean rank over the metrics (the paper shows 3); 0 = all."),
    figures: Optional[bool] = typer.Option(None, "--figures/--no-figures", help="Write the figures "
                                           "(default: only with --table all)."),
    trajectories: int = typer.Option(4, "--trajectories", help="Test trajectories in the trajectory figure."),
    latency: bool = typer.Option(True, "--latency/--no-latency", help="Ablation: measure latency/GMAC with "
                                 "`bronchopose profile` (without: those columns stay empty)."),
    latency_from: Optional[Path] = typer.Option(None, "--latency-from", help="Ablation: read latency/GMAC from "
                                                "`bronchopose profile --format json` output instead of measuring."),
    latency_device: str = typer.Option("cpu", "--latency-device", help="Ablation profiling device: cpu or cuda."),
    image_size: Optional[int] = typer.Option(None, "--image-size", help="Ablation profiling input size "
                                             "(default: data.image_size or dataset.generate.image_size)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Do not print the tables."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Build the paper's tables and figures from the sweep's FINISHED runs and write them to --out.

    Tables: personalized (Tables 2 accumulated / 3 per pair), cross-subject
    (Tables 4/5, pooled over the pairs/trajectories of every held-out patient),
    sota (Table 6, BronchoTrack vs OffsetNet) and ablation (params, latency,
    GMAC, position L2, CE per architecture). Cells are "mean ± population std";
    bold = best of its architecture group, red = best of the column, blue =
    second best (Markdown: bold, italic † / ‡). A cell without a FINISHED run
    shows "—" and is listed in a warning; of duplicate runs of one cell the
    latest FINISHED is used, with a warning. Figures (PNG + PDF): trajectories
    (ground truth vs BronchoTrack vs OffsetNet), error vs frame per
    architecture, dataset frames and positions. See docs/reports.md.
    """
    from ..reporting import collect  # lazy: keeps `bronchopose --help` fast
    from ..reporting import report as rep
    from ..reporting import tables as tbl
    from ..reporting.figures import mlflow_loader
    from ..reporting.markdown import to_rich

    names, evals, suffixes = tbl.table_names(table), tbl.evaluations(evaluation), rep.output_suffixes(fmt)
    if pose_frame is not None and pose_frame not in POSE_FRAMES:
        raise BronchoError(f"--pose-frame {pose_frame!r}: must be one of {', '.join(POSE_FRAMES)}")
    if best < 0 or trajectories < 1:
        raise BronchoError("--best must be >= 0 and --trajectories >= 1")
    cfg = load(config, profile, set_)
    client = rep.open_store(cfg)
    index = collect.collect_runs(client, cfg.experiment_name, sweep or cfg.name, pose_frame)
    console.print(rep.summary_index(index))
    ctx = tbl.ReportContext(index, best=best)
    if latency_from is not None:
        ctx.profiler = rep.profiles_from_json(latency_from)
    elif latency:
        measure = rep.measuring_profiler(image_size or rep.default_image_size(cfg), latency_device)

        def profiled(arch: str):
            with err_console.status(f"profiling {arch} for the ablation table ..."):
                return measure(arch)
        ctx.profiler = profiled
    else:
        ctx.profiler_note = "--no-latency"
    with_figures = table == "all" if figures is None else figures
    warnings: list[str] = []
    result = rep.make_report(
        ctx, names, evals, suffixes, out, loader=mlflow_loader(client, warnings) if with_figures else None,
        n_trajectories=trajectories, dataset_root=cfg.paths.dataset if with_figures else None,
        warnings=warnings,
    )
    if not quiet:
        for t in result.tables:
            console.print(to_rich(t))
    for w in dict.fromkeys([w for t in result.tables for w in t.warnings] + result.warnings):
        err_console.print(f"[yellow]warning:[/] {w}", highlight=False, soft_wrap=True)
    console.print(f"wrote {len(result.files)} file(s) to {out}/: " + ", ".join(p.name for p in result.files))
