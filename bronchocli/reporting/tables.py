"""The paper's tables built from a sweep's runs: a name -> builder registry.

``TABLES[name](ctx, evaluation)`` returns a ``table_model.Table``; ``evaluation``
is ``accumulated`` or ``pair``. A builder raises ``NoData`` when the table
does not apply to the runs (the report skips it with one warning). What each
table holds is documented in docs/reports.md; in short:

* ``personalized`` (Tables 2/3): 4 BronchoPose architectures x 3 rotation
  losses, personalized runs (the ``personalized`` stage of a staged plan);
* ``cross-subject`` (Tables 4/5): the same combinations (the selected ones of
  a staged plan), each replicate = one seed's runs over every held-out
  patient; ``ctx.best`` > 0 keeps the best N combinations by mean rank;
* ``sota`` (Table 6): BronchoTrack (the ``sota`` stage's selection, else
  ConvLSTM + MSE+CE) vs OffsetNet trained with MSE+MSE, with parameter counts;
* ``ablation``: params, latency and GMAC per architecture next to position L2
  and CE of its MSE+CE personalized runs;
* ``frames``: skill of world vs camera labels per architecture (frames_table);
* ``tracking``: the literature's camera-tracking metrics per network/loss
  (CTF, ATE, RPE over a frame gap, drift; odometry.py), personalized runs,
  built once whatever ``--eval`` says (its scope is the whole trajectory).

Every error cell is ``mean [95 % interval]`` with significance marks and two
image-blind reference rows (judge.py).
"""

from __future__ import annotations

import math
from typing import Callable, Mapping, Sequence

from .. import registry
from ..errors import BronchoError
from .aggregate import EVALS, nonfinite_rows
from .collect import RunRecord
from .context import (
    ABLATION_LOSS,
    EVAL_TEXT,
    IGNORES_TEXT,
    OFFSETNET,
    Collector,
    NoData,
    ReportContext,
    arch_names,
    bronchotrack,
    budget_text,
    finish,
    heading,
    init_text,
    losses,
    metrics_of,
    model_name,
    n_text,
    precision_text,
    provenance,
    references_text,
    units_text,
)
from .estimand import estimand_text, refused_text, unit_of
from .frames_table import frames
from .judge import Line, method_text, metric_rows, one_seed_text, unsettled_text
from .table_model import Column, Row, Table, Value

NUMBERS = {("personalized", "accumulated"): 2, ("personalized", "pair"): 3,
           ("cross-subject", "accumulated"): 4, ("cross-subject", "pair"): 5}

__all__ = ["TABLES", "ReportContext", "NoData", "table_names", "evaluations", "arch_names", "losses"]


def _metric_columns(names: Sequence[str]) -> list[Column]:
    return [Column(*heading(m)) for m in names]


def _build(ctx: ReportContext, c: Collector, table: Table, lines: Sequence[Line], metrics: Sequence[str],
           evaluation: str, extra: str = "", expected_empty: Sequence[str] = (), units: str = "",
           population: str = "personalized") -> Table:
    """Fill ``table`` from ``lines``: rows, reference rows, marks, skill, caption and warnings. ``units``: the
    caption's units (default: the paper tables' metrics, registry.py); each metric's direction is registry.py's.

    No line at all (none of the config's cells belongs to this table, e.g. Table 4 of a sweep without
    cross-subject cells): ``NoData``, so the report skips it with one warning instead of printing a table of
    reference rows only."""
    if not lines:
        raise NoData(f"{table.key.rsplit('-', 1)[0]} skipped: none of the runs' cells belongs to it "
                     f"({table.title.split('. ', 1)[-1]})")
    every = [r for line in lines for r in line.runs]
    frames = ctx.frames(every)
    unit = unit_of(population)
    higher = [m for m in metrics if registry.metric(m).higher_is_better]
    built = metric_rows(lines, frames, metrics, evaluation, grouped=table.grouped,
                        settings=ctx.settings, skill_metrics=metrics_of("skill"), higher=higher, unit=unit)
    table.rows, table.marks, table.skill, table.judged = built.rows, built.marks, built.skill, True
    parts = [f"{EVAL_TEXT[evaluation]}.", estimand_text(unit, table.rows), method_text(ctx.settings),
             n_text(table.rows, evaluation, sorted(c.folds)), refused_text(table.rows)]
    if extra:
        parts.append(extra)
    names = {m: heading(m)[0] for m in metrics}
    parts.append(unsettled_text(built.unsettled, names, table.rows))
    parts.append(one_seed_text(table.rows))
    parts.append(references_text())
    if any("ignores" in r.flags for r in table.rows):
        parts.append(IGNORES_TEXT)
    numerics, mixed = precision_text(table)
    parts += [numerics, budget_text(every), init_text(every), units or units_text(), provenance(ctx, c)]
    table.caption = " ".join(p for p in parts if p)
    finish(table, c, expected_empty)
    if mixed:
        table.warnings.append(mixed)
    if built.fallback:
        table.warnings.append(f"{table.key}: no trajectory_errors.csv for {', '.join(built.fallback)} "
                              f"({_why_missing(every, frames)}): logged means shown without interval, not ranked")
    dropped = nonfinite_rows(frames)
    if dropped:
        table.warnings.append(f"{table.key}: {sum(dropped.values())} trajectory row(s) with NaN/inf errors in the "
                              f"trajectory_errors.csv of {len(dropped)} run(s) ({', '.join(sorted(dropped))}) left "
                              "out of the means and intervals")
    return table


def _why_missing(runs: Sequence[RunRecord], frames: Mapping[str, object]) -> str:
    """The true reason runs lack trajectory_errors.csv: their artifact folder is gone, or they predate it."""
    gone = {r.run_id: r.artifacts_gone for r in runs if frames.get(r.run_id) is None}
    deleted = sorted(str(p) for p in gone.values() if p is not None)
    if deleted:
        return (f"the artifacts of {len(deleted)} run(s) were deleted or moved: {deleted[0]}"
                + (f" and {len(deleted) - 1} more" if len(deleted) > 1 else "") + " does not exist")
    return "runs made before it was logged, or whose artifact was removed"


def _grid_lines(c: Collector) -> list[Line]:
    """The paper's architecture x loss layout, restricted to the combinations of the table's cells."""
    return [c.line(group, label, arch, loss)
            for arch, group in arch_names(paper_tables=True).items() for loss, label in losses().items()
            if c.has(arch, loss)]


def personalized(ctx: ReportContext, evaluation: str) -> Table:
    c = Collector(ctx, "personalized", "personalized")
    n = NUMBERS[("personalized", evaluation)]
    table = Table(f"table{n}-personalized-{evaluation}", f"Table {n}. Personalized population, {evaluation} "
                  "evaluation", ("Network", "Loss"), _metric_columns(metrics_of("paper")), [])
    return _build(ctx, c, table, _grid_lines(c), metrics_of("paper"), evaluation)


def _mean_rank(rows: Sequence[Row], metrics: Sequence[str]) -> list[float]:
    """Per row, the mean over the metric columns of its rank (1 = the best mean: the lowest, the highest where
    higher is better; ties share the average rank)."""
    ranks = [0.0] * len(rows)
    for j, metric in enumerate(metrics):
        sign = -1.0 if registry.metric(metric).higher_is_better else 1.0
        means = [sign * r.values[j].mean for r in rows]  # type: ignore[union-attr]
        for i, m in enumerate(means):
            ranks[i] += sum(x < m for x in means) + (sum(x == m for x in means) + 1) / 2
    return [r / len(metrics) for r in ranks]


def _keep_best(table: Table, best: int, metrics: Sequence[str]) -> str:
    """Keep the best N model rows (and the reference rows) by mean rank over the metric means."""
    model = [i for i, r in enumerate(table.rows) if r.kind == "model"
             and all(v is not None and not math.isnan(v.mean) for v in r.values)]  # type: ignore[union-attr]
    ranks = dict(zip(model, _mean_rank([table.rows[i] for i in model], metrics)))
    chosen = set(sorted(model, key=lambda i: (ranks[i], table.rows[i].values[0].mean))[:best])  # type: ignore
    keep = [i for i, r in enumerate(table.rows) if i in chosen or r.kind != "model"]
    table.rows = [table.rows[i] for i in keep]
    table.marks = [table.marks[i] for i in keep] if table.marks is not None else None
    return (f"Showing the best {len(chosen)} of {len(model)} complete network/loss combinations, ranked by the "
            f"mean of their ranks over the {_count(len(metrics))} metric means (marks computed over all of them).")


def _count(n: int) -> str:
    return ("one", "two", "three", "four", "five", "six", "seven", "eight", "nine")[n - 1] if 0 < n < 10 else str(n)


def cross_subject(ctx: ReportContext, evaluation: str) -> Table:
    c = Collector(ctx, "cross-subject", "cross-subject")
    n = NUMBERS[("cross-subject", evaluation)]
    table = Table(f"table{n}-cross-subject-{evaluation}", f"Table {n}. Cross-subject population, {evaluation} "
                  "evaluation", ("Network", "Loss"), _metric_columns(metrics_of("paper")), [])
    lines = _grid_lines(c)
    pooled = ("Leave-one-patient-out: a replicate is one seed's runs over every held-out patient (held-out: "
              f"{', '.join(sorted(c.folds)) or '-'}); its value is the metric over the union of their test "
              f"{'pairs' if evaluation == 'pair' else 'trajectories'}.")
    _build(ctx, c, table, lines, metrics_of("paper"), evaluation, pooled, population="cross-subject")
    if ctx.best > 0:
        note = _keep_best(table, ctx.best, metrics_of("paper"))
        table.caption = table.caption.replace(pooled, f"{pooled} {note}")
    return table


def _params_m(c: Collector, runs, name: str) -> float | None:
    for r in runs or ():
        if "n_params" in r.metrics:
            return r.metrics["n_params"] / 1e6
    if runs:
        c.warn(f"missing: {name}: no run logged n_params")
    return None


def sota(ctx: ReportContext, evaluation: str) -> Table:
    c = Collector(ctx, "sota", "personalized")
    arch, loss, how = bronchotrack(ctx.index)
    lines = []
    for (a, lo), name in (((arch, loss), f"BronchoTrack ({model_name(arch)}, {losses().get(loss, loss)})"),
                          (OFFSETNET, "OffsetNet (MSE+MSE)")):
        if c.expected is not None and not c.wanted(a, lo):
            c.warn(f"sota: this config has no {a}/{lo} personalized cell, so the {name} row is empty")
        line = c.line("", name, a, lo)
        line.extra = [_params_m(c, line.runs, name)]
        lines.append(line)
    table = Table(f"table6-sota-{evaluation}", f"Table 6. State of the art, personalized population, {evaluation} "
                  "evaluation", ("Model",), [Column("Params", "M", highlight=False, decimals=3)]
                  + _metric_columns(metrics_of("paper")),
                  [])
    extra = (f"{how}; OffsetNet is trained with MSE on position and rotation, its original loss. Params: trainable "
             "parameters of the trained model (n_params), millions.")
    return _build(ctx, c, table, lines, metrics_of("paper"), evaluation, extra)


def _profile_values(ctx: ReportContext, c: Collector, arch: str, runs) -> list[Value]:
    prof = ctx.profile(arch)
    params = _params_m(c, runs, arch_names()[arch]) if runs else None
    if prof is None:
        return [params, None, None]
    if params is None and prof.get("params") is not None:
        params = float(prof["params"]) / 1e6
    return [params, prof.get("latency_ms_b1"), prof.get("gmacs_per_pair")]


def _profile_caption(ctx: ReportContext) -> str:
    profs = [p for p in ctx._profiles.values() if p]
    if not profs:
        return f"Latency and GMAC not measured ({ctx.profiler_note or 'no profiler'})."
    p = profs[0]
    return (f"Latency: median time of one forward over a window of {p.get('window', '?')} pairs at batch 1 divided "
            f"by its pairs, on {p.get('device', '?')}, {p.get('image_size', '?')}x{p.get('image_size', '?')} input, "
            f"precision {p.get('precision', '?')}; GMAC: convolution/linear multiply-accumulates per pair "
            f"(bronchopose profile).")


def ablation(ctx: ReportContext, evaluation: str) -> Table:
    c = Collector(ctx, "ablation", "personalized")
    lines = []
    for arch, name in arch_names().items():
        if not c.has(arch, ABLATION_LOSS):
            continue
        line = c.line("", name, arch, ABLATION_LOSS)
        line.extra = _profile_values(ctx, c, arch, line.runs)
        lines.append(line)
    columns = [Column("Params", "M", highlight=False, decimals=3),
               Column("Latency", "ms/pair", highlight=False, decimals=2),
               Column("GMAC/pair", highlight=False, decimals=3)] + _metric_columns(metrics_of("ablation"))
    table = Table(f"table7-ablation-{evaluation}", f"Ablation: cost and accuracy per architecture, personalized "
                  f"population, {evaluation} evaluation", ("Network",), columns, [])
    extra = (f"Every architecture trained with {losses()[ABLATION_LOSS]}; only the error columns are judged. "
             + _profile_caption(ctx))
    unmeasured = [col.heading for col in columns[1:3]] if ctx.profiler is None else []
    return _build(ctx, c, table, lines, metrics_of("ablation"), evaluation, extra, unmeasured)


# The literature's definitions of the tracking table's metrics (registry.py names, labels and units them).
TRACKING_UNITS = ("CTF: share of frames 1..N-1 (the first pose is given) whose position error is below the position "
                  "threshold and whose rotation error (geodesic angle) is below the angle threshold, %, higher is "
                  "better; CTF mm (the literature's threshold, in mm from the dataset's voxel spacing) is the primary "
                  "column, CTF vox (the threshold in voxels) the secondary one; its interval is built on the logit "
                  "scale, so it stays within 0-100%; ATE: RMSE of the "
                  "position error over every frame, no alignment, voxels and mm; RPE: RMSE over every frame i of "
                  "the error of the relative motion from frame i to i + gap (translation in voxels, rotation in "
                  "degrees; TUM definition); Drift: final position error / ground-truth path length, %. Lower is "
                  "better except CTF: in the CTF columns the best is the highest mean and † means the interval does "
                  "not lie above the better reference's mean.")


def _thresholds_text(c: Collector, runs) -> str:
    """The thresholds the runs logged (eval.* params; metrics on runs logged before); a warning when they differ."""
    names = {"eval.ctf_position": "{:g} voxels", "eval.ctf_position_mm": "{:g} mm", "eval.ctf_angle": "{:g}°",
             "eval.rpe_gap": "{:g} frames"}
    seen = {k: sorted({v for r in runs if (v := r.setting(k)) is not None}) for k in names}
    if not any(seen.values()):
        return "Thresholds: not logged by these runs."
    for k, values in seen.items():
        if len(values) > 1:
            c.warn(f"tracking: the runs used different {k} ({', '.join(f'{v:g}' for v in values)}); their CTF/RPE "
                   f"are not comparable")
    text = {k: "/".join(fmt.format(v) for v in seen[k]) or "?" for k, fmt in names.items()}
    return (f"Thresholds (config eval:): position {text['eval.ctf_position_mm']} (CTF mm) / "
            f"{text['eval.ctf_position']} (CTF vox), angle {text['eval.ctf_angle']}; RPE gap {text['eval.rpe_gap']} "
            f"(a test trajectory shorter than the gap has no RPE and is left out of those columns).")


def tracking(ctx: ReportContext, evaluation: str) -> Table:
    """The literature's camera-tracking metrics (the paper's Table 1 and the visual-odometry benchmarks)."""
    del evaluation  # whole-trajectory metrics: one table
    c = Collector(ctx, "tracking", "personalized")
    labels = losses()
    lines = [c.line(name, labels[loss], arch, loss)
             for arch, name in arch_names().items() for loss in labels if c.has(arch, loss)]
    every = [r for line in lines for r in line.runs]
    order = tracking_order(every)
    table = Table("table9-tracking", "Table 9. Camera tracking: CTF, ATE, RPE and drift, personalized population",
                  ("Network", "Loss"), _metric_columns(order), [])
    return _build(ctx, c, table, lines, order, "trajectory", _thresholds_text(c, every), units=TRACKING_UNITS)


def tracking_order(runs: Sequence[RunRecord]) -> list[str]:
    """The tracking columns: mm first where the runs know the voxel spacing (a finite ``traj.ctf_mm.mean``),
    voxels first where none does (e.g. imported poses without spacing)."""
    known = any(math.isfinite(r.metrics.get("traj.ctf_mm.mean", math.nan)) for r in runs)
    order = metrics_of("tracking")
    return mm_first(order) if known or not runs else order


def mm_first(names: Sequence[str]) -> list[str]:
    """Each metric's mm twin (``<name>_mm``, registry.MetricSpec) just before it: the literature's units lead."""
    out: list[str] = []
    for m in names:
        if m.endswith("_mm") and m[:-3] in names:
            continue  # placed with its twin
        out += [f"{m}_mm", m] if f"{m}_mm" in names else [m]
    return out


ONCE = {"tracking"}  # tables built once, not per evaluation


TABLES: dict[str, Callable[[ReportContext, str], Table]] = {
    "personalized": personalized,
    "cross-subject": cross_subject,
    "sota": sota,
    "ablation": ablation,
    "frames": frames,
    "tracking": tracking,
}


def table_names(name: str) -> list[str]:
    """``all`` or one registered table name -> the names to build (BronchoError lists the valid ones)."""
    if name == "all":
        return list(TABLES)
    if name not in TABLES:
        raise BronchoError(f"--table {name!r}: must be one of all, {', '.join(TABLES)}")
    return [name]


def evaluations(name: str) -> list[str]:
    if name == "both":
        return list(EVALS)
    if name not in EVALS:
        raise BronchoError(f"--eval {name!r}: must be one of accumulated, pair, both")
    return [name]
