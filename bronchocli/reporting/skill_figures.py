"""Skill figures (one per table) and the learning curve (error and skill against training-set size).

* ``fig-skill-<table>``: skill = 1 - error / error of the better image-blind
  reference, one bar per model row with its 95 % interval (t interval
  on variance components over seeds and test trajectories, delta method), one
  panel per error column of the table (position, rotation L2, DE, CE) in its
  evaluation. 0 = no better than an image-blind model; below 0 = worse. A
  lower bound that touches 0 (within 2 % of the panel's range) is written out,
  so −0.003 does not read as 0 or above it; the title says which rows have no
  bar only where some have none.
* ``fig-learning-curve``: when the runs span several ``train_trajectories``
  values, per architecture (x loss) the per-pair position and rotation L2 and
  their skill against the training pairs (``train.train_pairs``), with 95 %
  intervals and the two references (dashed); the top axis gives the training
  trajectories per patient and lobe.
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Sequence

import matplotlib.pyplot as plt
import numpy as np

from .. import registry, runkeys
from ..io import save_figure
from .aggregate import REFERENCES
from .collect import FRAME, POP, size_key
from .context import Collector, ReportContext, arch_names, heading, losses, metrics_of
from .estimand import ESTIMAND_NAMES, unit_of
from .judge import beats_reference, metric_rows
from .table_model import Estimate, Table

FORMATS = ("png", "pdf")
CURVE_EVAL = "pair"
TRAIN_PAIRS = runkeys.train("train_pairs")  # the x of the learning curve


TOUCHES = 0.02  # a bound within this share of a panel's y range of 0 "touches" 0: its value is written out


def skill_figure(table: Table):
    """Bars of each model row's skill, one panel per error column of the table, with intervals; None when the
    table has none."""
    names = [r.name for r in table.rows if r.kind == "model" and r.name in table.skill]
    if not names:
        return None
    metrics = [m for m in registry.metric_names() if any(m in table.skill[n] for n in names)]
    cols = min(len(metrics), 2)
    rows = -(-len(metrics) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(max(4.0, 0.55 * len(names) + 2.0) * cols, 3.6 * rows + 0.4),
                             squeeze=False)
    for ax in axes.flat[len(metrics):]:
        ax.set_visible(False)
    touching = False
    for ax, m in zip(axes.flat, metrics):
        d = [table.skill[n].get(m) for n in names]
        x = np.arange(len(names))
        val = np.array([np.nan if s is None else s.value for s in d])
        err = np.array([[0.0, 0.0] if s is None else [s.value - s.lo, s.hi - s.value] for s in d]).T
        colors = ["tab:blue" if s is not None and beats_reference(s) else "0.6" for s in d]  # the † verdict
        ax.bar(x, val, color=colors, yerr=err, capsize=3)
        ax.axhline(0.0, color="black", lw=0.8)
        ax.set_xticks(x, names, rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(f"skill, {heading(m)[0]}")
        ax.set_title(f"{heading(m)[0]}: 1 − error / better reference", fontsize=9)
        ax.grid(axis="y", alpha=0.3)
        low, high = ax.get_ylim()
        for i, s in enumerate(d):
            if s is not None and abs(s.lo) <= TOUCHES * (high - low):  # e.g. -0.003: say it, it is not 0
                touching = True
                ax.annotate(f"{s.lo:+.3g}", (i, s.lo), xytext=(4, -2), textcoords="offset points", fontsize=7,
                            color="tab:red" if s.lo <= 0 else "tab:blue", va="top")
    units = {x.unit for r in table.rows if r.kind == "model" for x in r.info.get("samples", ()) if x is not None}
    about = ESTIMAND_NAMES.get(units.pop() if len(units) == 1 else "", "its table's estimand")
    lines = [table.title, f"bars: skill with 95% interval (estimand: {about}); blue = interval above 0 (beats the "
                          f"better reference: no † in the table), grey = not"]
    if touching:
        lines[-1] += "; a lower bound at 0 is written out (red: ≤ 0)"
    without = [r.name for r in table.rows if r.kind == "model" and r.runs and r.name not in table.skill]
    if without:
        refused = {r.name for r in table.rows if r.info.get("refused")}
        why = "means only: too few patients" if set(without) <= refused else "no per-trajectory errors"
        lines.append(f"no bar for {', '.join(without)} ({why})")
    width = int(fig.get_figwidth() * 15)  # characters of fontsize 8 across the figure
    fig.suptitle("\n".join(textwrap.fill(line, width) for line in lines), fontsize=8)
    fig.tight_layout()
    return fig


def skill_figures(tables: Sequence[Table], out: Path, warnings: list[str]) -> list[Path]:
    written: list[Path] = []
    for t in tables:
        fig = skill_figure(t)
        if fig is None:
            skill_columns = {heading(m)[0] for m in metrics_of("skill")}
            if t.judged and any(c.title in skill_columns for c in t.columns):  # tracking: no skill columns by design
                warnings.append(f"figures: fig-skill-{t.key} skipped (no row with per-trajectory errors)")
            continue
        written += save_figure(fig, Path(out) / f"fig-skill-{t.key}", FORMATS)
    return written


def _curve_population(ctx: ReportContext) -> str:
    pops = {i[POP] for i in ctx.index.runs if i[FRAME] == ctx.index.pose_frame}
    return "personalized" if "personalized" in pops else "cross-subject"


def _size_label(size: str, ctx: ReportContext) -> str:
    if size:
        return size
    return str(ctx.default_train_trajectories) if ctx.default_train_trajectories else "default"


def curve_points(ctx: ReportContext) -> dict:
    """Per training-set size: x (training pairs), each series' estimates and skill, the references."""
    population = _curve_population(ctx)
    sizes = ctx.index.sizes(population)
    points = {}
    for size in sizes:
        c = Collector(ctx, "learning", population, size=size)
        archs, used = c.combos()
        lines = [c.line(a, lo) for a in arch_names() if a in archs for lo in losses() if lo in used]
        lines = [ln for ln in lines if ln.runs]
        if not lines:
            continue
        every = [r for ln in lines for r in ln.runs]
        built = metric_rows(lines, ctx.frames(every), metrics_of("skill"), CURVE_EVAL, grouped=False,
                            settings=ctx.settings, skill_metrics=metrics_of("skill"), unit=unit_of(population))
        pairs = [r.metrics[TRAIN_PAIRS] for r in every if TRAIN_PAIRS in r.metrics]
        points[size] = {"x": float(np.mean(pairs)) if pairs else float("nan"), "rows": built.rows,
                        "skill": built.skill, "label": _size_label(size, ctx)}
    return {"population": population, "points": points}


def learning_curve_figure(ctx: ReportContext):
    """The learning curve, or None when the runs do not span several training-set sizes."""
    data = curve_points(ctx)
    points = data["points"]
    if len(points) < 2:
        return None
    sizes = sorted(points, key=size_key)
    xs = np.array([points[s]["x"] for s in sizes])
    if np.isnan(xs).any():  # runs without train.train_pairs: fall back to the size order
        xs = np.arange(len(sizes), dtype=float) + 1.0
    skill_metrics = metrics_of("skill")
    fig, axes = plt.subplots(len(skill_metrics), 2, figsize=(10, 3.6 * len(skill_metrics)), squeeze=False)
    series = sorted({r.name for s in sizes for r in points[s]["rows"] if r.kind == "model"})
    for j, m in enumerate(skill_metrics):
        err_ax, skill_ax = axes[j]
        for name in series:
            est = [next((r.values[j] for r in points[s]["rows"] if r.name == name), None) for s in sizes]
            _plot_series(err_ax, xs, est, name)
            sk = [points[s]["skill"].get(name, {}).get(m) for s in sizes]
            _plot_series(skill_ax, xs, [None if d is None else Estimate(d.value, d.lo, d.hi) for d in sk], name)
        for ref, style in zip(REFERENCES.values(), ("--", ":")):
            est = [next((r.values[j] for r in points[s]["rows"] if r.name == f"{ref}"), None) for s in sizes]
            ys = [e.mean if isinstance(e, Estimate) else np.nan for e in est]
            err_ax.plot(xs, ys, style, color="black", lw=1, label=ref)
        skill_ax.axhline(0.0, color="black", lw=0.8, ls="--", label="better reference")
        title, symbol = heading(m)
        err_ax.set_ylabel(f"{title} per pair ({symbol})")
        skill_ax.set_ylabel(f"skill, {title}")
        for ax in (err_ax, skill_ax):
            ax.set_xscale("log")
            ax.minorticks_off()
            ax.set_xticks(xs, [f"{x:,.0f}" for x in xs])
            ax.set_xlabel("training pairs")
            ax.grid(alpha=0.3)
            top = ax.secondary_xaxis("top")
            top.minorticks_off()
            top.set_xticks(xs, [points[s]["label"] for s in sizes], fontsize=7)
            top.set_xlabel("training trajectories per patient and lobe", fontsize=7)
        if j == 0:
            err_ax.legend(fontsize=6)
            skill_ax.legend(fontsize=6)
    about = ESTIMAND_NAMES[unit_of(data["population"])]
    fig.suptitle(f"Learning curve, {data['population']} population, per-pair evaluation: mean with 95% interval "
                 f"(estimand: {about}); skill = 1 − error / better image-blind reference", fontsize=8)
    fig.tight_layout()
    return fig


def _plot_series(ax, xs: np.ndarray, est: Sequence, name: str) -> None:
    ok = [i for i, e in enumerate(est) if isinstance(e, Estimate)]
    if not ok:
        return
    x = xs[ok]
    y = np.array([est[i].mean for i in ok])
    lo = np.array([est[i].lo if est[i].has_interval else est[i].mean for i in ok])
    hi = np.array([est[i].hi if est[i].has_interval else est[i].mean for i in ok])
    ax.errorbar(x, y, yerr=[y - lo, hi - y], marker="o", ms=3, capsize=3, lw=1.2, label=name)


def learning_curve(ctx: ReportContext, out: Path, warnings: list[str]) -> list[Path]:
    """Write fig-learning-curve when the runs span several training-set sizes (else nothing)."""
    if len(ctx.index.sizes(_curve_population(ctx))) < 2:
        return []
    fig = learning_curve_figure(ctx)
    if fig is None:
        warnings.append("figures: fig-learning-curve skipped: fewer than two training-set sizes have runs")
        return []
    return save_figure(fig, Path(out) / "fig-learning-curve", FORMATS)
