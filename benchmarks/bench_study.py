"""A finished study read back into a results file: every cell's test ratios, mode gap and cost, and its report.

    python benchmarks/bench_study.py PROJECT [--profile NAME] [--set KEY=VALUE ...] --out NAME [--reports DIR]
        [--command TEXT]

PROJECT is the folder the study ran in (its experiments.yaml, MLflow store and claims table; the main job's is
the clone it ran in). For every finished cell run of the config's experiment (parents and tune trials left
out) it records the cell's coordinates and what the paper's tables compare, from the run's own metrics: the
per-pair position and rotation (L2) error ÷ the training-mean reference's on the same test pairs
(``pair.<m>.mean / train_mean.pair.<m>.mean``), the accumulated (per-trajectory) position ratio, ``eval.mode_gap``,
the parameter count, and the cost of learning (``cost.pairs_to_0.90``, ``cost.core_s_to_0.90``, ``train.core_s``).
The report's Markdown tables (``--reports``, default PROJECT/reports) are kept verbatim as ``docs_*`` line lists:
benchmarks/README.md shows them as generated blocks (``python benchmarks/docblocks.py --write``).
Writes benchmarks/results/NAME.json atomically, with this machine's CPU line: run it where the study trained.
Nothing here trains anything.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import statistics
import sys
from pathlib import Path
from typing import Any

from bench_common import cpu_line

from bronchocli.config import load_config
from bronchocli.runs.client import client_for
from bronchocli.training.cost import COST_TARGET

HERE = Path(__file__).resolve().parent
COORDS = ("arch", "rot_loss", "population", "fold", "seed", "pose_frame")


def ratio(m: dict[str, float], metric: str, unit: str = "pair") -> float | None:
    """The model's error ÷ the training mean's on the same test pairs (unit ``pair``) or trajectories (``acc``)."""
    own, ref = m.get(f"{unit}.{metric}.mean"), m.get(f"train_mean.{unit}.{metric}.mean")
    return own / ref if own is not None and ref else None


def cell_row(run) -> dict[str, Any]:
    p, m = run.data.params, run.data.metrics
    row: dict[str, Any] = {k: p.get(k) for k in COORDS}
    row.update({
        "run_id": run.info.run_id, "name": run.data.tags.get("mlflow.runName", ""), "status": run.info.status,
        "ratio_pos_pair": ratio(m, "pos_l2"), "ratio_rot_pair": ratio(m, "rot_l2"),
        "ratio_pos_acc": ratio(m, "pos_l2", "acc"),
        "pos_l2_pair": m.get("pair.pos_l2.mean"), "train_mean_pos_l2_pair": m.get("train_mean.pair.pos_l2.mean"),
        "mode_gap": m.get("eval.mode_gap"), "val_best_ratio": m.get("val_best.ratio.pos_l2"),
        "n_params": m.get("n_params"), "pairs_seen": m.get("train.pairs_seen"), "core_s": m.get("train.core_s"),
        "pairs_to_target": m.get(f"cost.pairs_to_{COST_TARGET:.2f}"),
        "core_s_to_target": m.get(f"cost.core_s_to_{COST_TARGET:.2f}"),
    })
    return row


def collect(cfg) -> list[dict[str, Any]]:
    client = client_for(cfg)
    exp = client.get_experiment_by_name(cfg.name)
    if exp is None:
        sys.exit(f"no MLflow experiment {cfg.name!r} in {cfg.runs.uri}: run the study first")
    runs = client.search_runs([exp.experiment_id], "attributes.status = 'FINISHED'", max_results=5000)
    return [cell_row(r) for r in runs if r.data.tags.get("run_kind", "cell") == "cell" and "arch" in r.data.params]


def summarise(cells: list[dict[str, Any]]) -> dict[str, Any]:
    """Per (arch, rot_loss, population[, held-out patient]): the seeds' ratios (range and mean) and the largest
    mode gap. Cross-subject cells are grouped per fold (the held-out patient)."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for c in cells:
        fold = f"/{c['fold']}" if c["population"] == "cross-subject" and c.get("fold") else ""
        groups.setdefault(f"{c['arch']}/{c['rot_loss']}/{c['population']}{fold}", []).append(c)
    out = {}
    for key, rows in sorted(groups.items()):
        entry: dict[str, Any] = {"seeds": sorted(int(r["seed"]) for r in rows)}
        for k in ("ratio_pos_pair", "ratio_rot_pair", "ratio_pos_acc", "mode_gap", "pairs_to_target",
                  "core_s_to_target", "core_s", "n_params"):
            vals = [r[k] for r in rows if r[k] is not None]
            entry[k] = sorted(round(v, 4) for v in vals)
            if vals:
                entry[f"{k}_mean"] = statistics.fmean(vals)
        out[key] = entry
    return out


def cells_table(by_model: dict[str, Any]) -> list[str]:
    """A compact Markdown table of :func:`summarise`: per model and loss, every seed's ratios and cost."""
    def j(v: list, spec: str) -> str:
        return " / ".join(format(x, spec) for x in v) if v else "–"
    folds = any(len(key.split("/")) > 3 for key in by_model)
    lines = [f"| model | loss |{' held out |' if folds else ''} seeds | position ÷ training mean (pair) "
             "| rotation ÷ (pair) | position ÷ (accumulated) | mode gap | pairs to 0.90 |",
             "|---|---|" + ("---|" if folds else "") + "---|---|---|---|---|---|"]
    for key, e in by_model.items():
        arch, loss, *rest = key.split("/")
        held = f" {rest[1]} |" if folds else ""
        lines.append(f"| {arch} | {loss} |{held} {j(e['seeds'], 'd')} | {j(e['ratio_pos_pair'], '.3f')} "
                     f"| {j(e['ratio_rot_pair'], '.3f')} | {j(e['ratio_pos_acc'], '.2f')} | {j(e['mode_gap'], '.3f')} "
                     f"| {j(e['pairs_to_target'], ',.0f')} |")
    return lines


def flat(by_model: dict[str, Any]) -> dict[str, dict[str, list]]:
    """The per-seed figures keyed ``arch-loss`` (a document's span path cannot hold the ``/`` of by_model's keys);
    cross-subject groups also per fold, ``arch-loss-<held-out patient>``, with ``arch-loss`` pooling the folds."""
    out: dict[str, dict[str, list]] = {"ratio_pos": {}, "ratio_rot": {}, "ratio_pos_acc": {}, "mode_gap": {},
                                       "core_s": {}}
    for key, e in by_model.items():
        parts = key.split("/")
        names = ["-".join(parts[:2])] + (["-".join([*parts[:2], parts[3]])] if len(parts) > 3 else [])
        for field, src in (("ratio_pos", "ratio_pos_pair"), ("ratio_rot", "ratio_rot_pair"),
                           ("ratio_pos_acc", "ratio_pos_acc"), ("mode_gap", "mode_gap"), ("core_s", "core_s")):
            for i, name in enumerate(names):
                pooled = i == 0 and len(parts) > 3  # the folds of one model pooled under arch-loss
                out[field][name] = sorted([*out[field].get(name, []), *e[src]]) if pooled else e[src]
    out["mode_gap"]["all"] = sorted(x for e in by_model.values() for x in e["mode_gap"])
    return out


def report_tables(folder: Path) -> dict[str, list[str]]:
    """The report's Markdown tables, verbatim (one list of lines per file) but for their links to the report's own
    files (``[Methods](methods.md)``), which resolve in the report's folder, not where the docs show the tables:
    kept as text naming the file."""
    def unlinked(text: str) -> str:
        return re.sub(r"\[([^\]]+)\]\(([\w.-]+\.md)\)", r"\1 (the report's \2)", text)

    return {f"docs_{p.stem.replace('-', '_')}": unlinked(p.read_text()).rstrip("\n").splitlines()
            for p in sorted(folder.glob("*.md"))} if folder.is_dir() else {}


def marks(tables: dict[str, list[str]]) -> dict[str, dict[str, int]]:
    """Per report table, how many model rows carry † (does not beat the better image-blind reference) in each
    metric column, and how many model rows there are (``rows``): the tables' verdicts as figures."""
    out: dict[str, dict[str, int]] = {}
    for key, lines in tables.items():
        rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines if line.startswith("|")]
        if len(rows) < 3:
            continue
        head, body = rows[0], [r for r in rows[2:] if "reference" not in " ".join(r[:2]).lower()
                                and not any(w in " ".join(r[:2]) for w in ("Zero motion", "Training mean"))]
        counts = {"rows": len(body)}
        for i, name in enumerate(head):
            if ("(" in name or name == "CE") and not name.startswith("Params"):  # a metric column
                counts[name] = sum("†" in r[i] for r in body if i < len(r))
        out[key.removeprefix("docs_")] = counts
    return out


def folder_mb(path: Path) -> float:
    """Bytes of every file under ``path`` (links not followed), in MB (10^6)."""
    return round(sum(f.lstat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink()) / 1e6, 1)


PHASES = ("clone_venv_s", "torch_s", "project_s", "install_s", "sweep_s", "report_s", "total_s")


def phases(path: Path) -> dict[str, float]:
    """The ``NAME SECONDS`` lines main_job_phases.sh prints last."""
    out = {}
    for line in path.read_text().splitlines():
        name, _, value = line.partition(" ")
        if name in PHASES:
            out[name] = float(value)
    missing = [p for p in PHASES if p not in out]
    if missing:
        sys.exit(f"{path}: no {', '.join(missing)} line (the output of benchmarks/main_job_phases.sh?)")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project", type=Path, help="the folder the study ran in (experiments.yaml + runs/)")
    ap.add_argument("--profile", default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override the study ran with (e.g. name=probe: its MLflow experiment)")
    ap.add_argument("--out", required=True, help="results file name, without .json")
    ap.add_argument("--reports", type=Path, default=None, help="the report's folder (default PROJECT/reports)")
    ap.add_argument("--command", default=None, help="the command that ran the study (recorded)")
    ap.add_argument("--title", default=None)
    ap.add_argument("--wall-s", type=float, default=None, help="the study's measured wall time (recorded)")
    ap.add_argument("--phases", type=Path, default=None,
                    help="the output of benchmarks/main_job_phases.sh: its phases (clone_venv_s ... total_s) are "
                         "recorded as figures")
    args = ap.parse_args(argv)
    cfg = load_config(args.project / "experiments.yaml", args.profile, args.overrides)
    cells = collect(cfg)
    if not cells:
        sys.exit(f"no finished cell runs in experiment {cfg.name!r}")
    figures = {"experiment": cfg.name, "cells": sorted(cells, key=lambda c: tuple(str(c[k]) for k in COORDS)),
               "by_model": summarise(cells), "n_cells": len(cells),
               "docs_cells": cells_table(summarise(cells)),
               **flat(summarise(cells)),
               "max_mode_gap": max((c["mode_gap"] for c in cells if c["mode_gap"] is not None), default=None),
               **report_tables(args.reports or args.project / "reports")}
    figures["daggers"] = marks({k: v for k, v in figures.items() if k.startswith("docs_table")})
    # the tables alone (their header and rows, without title and caption, whose links are relative to reports/)
    figures |= {k.replace("docs_", "table_only_", 1): [line for line in v if line.startswith("|")]
                for k, v in list(figures.items()) if k.startswith("docs_table")}
    for key in ("ratio_pos", "ratio_pos_acc", "ratio_rot"):  # every cell's, for a study-wide range
        figures[f"all_{key}"] = sorted(v for vals in figures.get(key, {}).values() for v in vals if v is not None)
    if args.wall_s is not None:
        figures["wall_s"] = args.wall_s
    if args.phases is not None:
        figures |= phases(args.phases)
        # what the main job left on disk in its clone (the README's prerequisites): MB per folder and in all
        sizes = {name: folder_mb(args.project / name) for name in (".venv", "data", "runs", "reports")}
        figures["disk_mb"] = {**{k.lstrip("."): v for k, v in sizes.items()}, "total": folder_mb(args.project)}
    out = {"title": args.title or f"Study {cfg.name}: every finished cell's test ratios, mode gap and cost",
           "machine": cpu_line(), "date": dt.date.today().isoformat(),
           "command": args.command or f"bronchopose sweep run{' --profile ' + args.profile if args.profile else ''}",
           "figures": figures}
    path = HERE / "results" / f"{args.out}.json"
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1, ensure_ascii=False) + "\n")
    tmp.replace(path)
    print(f"wrote {path} ({len(cells)} cells)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
