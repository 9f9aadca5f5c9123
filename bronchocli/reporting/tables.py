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

from .. import registry, runkeys
from ..errors import BronchoError
from ..runs.records import TAG_INIT
from ..runs.views import EVAL_PARAMS
from .aggregate import EVALS, nonfinite_rows
from .captions import budget_text, caption, dataset_text, fixed_seeds_note, init_text, rot_scale_text
from .collect import RunRecord
from .context import (
    ABLATION_LOSS,
    BRONCHOTRACK,
    OFFSETNET,
    Collector,
    NoData,
    ReportContext,
    arch_names,
    bronchotrack,
    finish,
    heading,
    losses,
    metrics_of,
    precision_text,
    source_text,
)
from .estimand import patients_of, unit_of
from .frames_table import frames
from .judge import Line, metric_rows
from .table_model import Column, Row, Table, Value

NUMBERS = {("personalized", "accumulated"): 2, ("personalized", "pair"): 3,
           ("cross-subject", "accumulated"): 4, ("cross-subject", "pair"): 5}

__all__ = ["TABLES", "ReportContext", "NoData", "table_names", "evaluations", "arch_names", "losses"]


def _metric_columns(names: Sequence[str]) -> list[Column]:
    return [Column(*heading(m)) for m in names]


def _build(ctx: ReportContext, c: Collector, table: Table, lines: Sequence[Line], metrics: Sequence[str],
           evaluation: str, what: str, notes: Sequence[str] = (), expected_empty: Sequence[str] = (),
           population: str = "personalized") -> Table:
    """Fill ``table`` from ``lines``: rows, reference rows, marks, skill, caption (``what`` is compared: its first
    sentence; captions.py), notes (``notes`` and those that apply), source and warnings.

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
                        settings=ctx.settings, higher=higher, unit=unit,
                        skill_metrics=[m for m in metrics if registry.metric(m).per == "pose"])
    table.rows, table.marks, table.skill, table.judged = built.rows, built.marks, built.skill, True
    table.caption = caption(what, table.rows, evaluation, unit, folds=sorted(c.folds),
                            higher=[heading(m)[0] for m in higher])
    source, numerics, mixed = precision_text(table)
    table.notes = [n for n in (fixed_seeds_note(table.rows), *notes, numerics) if n]
    if built.fallback:
        table.notes.append(f"Logged means without interval, not ranked ({', '.join(built.fallback)}): their runs "
                           f"have no per-trajectory errors; † there means the mean does not lie below the better "
                           f"reference's.")
    table.source = [p for p in (source_text(ctx, c), budget_text(every), init_text(every), rot_scale_text(every),
                                dataset_text(every), source) if p]
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


REFERENCES = "two image-blind references"


def _why_missing(runs: Sequence[RunRecord], frames: Mapping[str, object]) -> str:
    """The true reason runs lack trajectory_errors.csv: their artifact folder is gone, or they predate it."""
    gone = {r.run_id: r.artifacts_gone for r in runs if frames.get(r.run_id) is None}
    deleted = sorted(str(p) for p in gone.values() if p is not None)
    if deleted:
        return (f"the artifacts of {len(deleted)} run(s) were deleted or moved: {deleted[0]}"
                + (f" and {len(deleted) - 1} more" if len(deleted) > 1 else "") + " does not exist")
    return "runs made before it was logged, or whose artifact was removed"


def _grid_lines(c: Collector) -> list[Line]:
    """The paper's architecture x loss layout, restricted to the combinations of the table's cells; a planned
    cell of an architecture outside the paper's groups (OffsetNet in a config without stages) gets its row after
    them, never left out silently. No paper cell at all: no line (the table does not apply; Table 6 has
    OffsetNet)."""
    paper = arch_names(paper_tables=True)
    if not any(c.has(arch, loss) for arch in paper for loss in losses()):
        return []
    return [c.line(arch, loss, grouped=True) for arch in arch_names() for loss in losses()
            if (c.has(arch, loss) if arch in paper else c.ran(arch, loss))]


def paper_cells() -> list[tuple[str, str]]:
    """The (arch, rot_loss) cells of the paper's Tables 2/3: its row groups x its rotation losses (registry.py)."""
    return [(a.name, lo) for a in registry.table_order() if a.paper_tables and a.paper_row is not None
            for lo in losses()]


def unplanned(ctx: ReportContext, c: Collector, population: str) -> tuple[str, str]:
    """(note, warning) when the config plans only some of the paper's cells of this table: which it lacks and
    the profiles of the config's file that plan them; ("", "") when it plans them all (or in sweep mode)."""
    if c.expected is None:
        return "", ""
    planned = {(i[0], i[1]) for i in c.expected}
    paper = paper_cells()
    missing = [cell for cell in paper if cell not in planned]
    if not missing:
        return "", ""
    groups: dict[str, list[str]] = {}
    for arch, loss in missing:
        groups.setdefault(registry.arch(arch).label, []).append(losses()[loss])
    named = "; ".join(f"{g}: {', '.join(ls)}" for g, ls in groups.items())
    need = {(a, lo, population) for a, lo in missing}
    plans = ctx.planned_by()
    full = [p for p, combos in plans.items() if need <= combos]
    some = [(p, len(need & combos)) for p, combos in plans.items() if need & combos and p not in full]
    if full:
        where = (f"the profile{'s' if len(full) > 1 else ''} {', '.join(full)} plan{'' if len(full) > 1 else 's'} "
                 f"them (bronchopose report --profile {full[0]})")
    elif some:
        where = "partly planned by " + ", ".join(f"the profile {p} ({n})" for p, n in some)
    else:
        where = "no profile of this config's file plans them"
    note = (f"This config plans {len(paper) - len(missing)} of the paper's {len(paper)} {population} network/loss "
            f"cells; not planned: {named}; {where}.")
    return note, f"{c.table}: {note}"


def personalized(ctx: ReportContext, evaluation: str) -> Table:
    c = Collector(ctx, "personalized", "personalized")
    n = NUMBERS[("personalized", evaluation)]
    table = Table(f"table{n}-personalized-{evaluation}", f"Table {n}. Personalized population, {evaluation} "
                  "evaluation", ("Network", "Loss"), _metric_columns(metrics_of("paper")), [])
    lines = _grid_lines(c)
    what = (f"Networks and rotation losses ({_combinations(lines)}) against {REFERENCES}, trained and "
            f"tested on the same patients (personalized population)")
    note, warning = unplanned(ctx, c, "personalized")
    _build(ctx, c, table, lines, metrics_of("paper"), evaluation, what, [note] if note else [])
    if warning:
        table.warnings.append(warning)
    return table


def _combinations(lines: Sequence[Line]) -> str:
    return f"{len(lines)} combination{'s' if len(lines) != 1 else ''}"


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
    what = (f"Networks and rotation losses ({_combinations(lines)}) against {REFERENCES}, "
            f"leave-one-patient-out: each model is tested on the patient it did not see (cross-subject population)")
    pooled = (f"A replicate is one seed's models over every held-out patient ({', '.join(sorted(c.folds)) or '-'}), "
              f"scored on the union of their test {'pairs' if evaluation == 'pair' else 'trajectories'}.")
    _build(ctx, c, table, lines, metrics_of("paper"), evaluation, what, [pooled], population="cross-subject")
    if ctx.best > 0:
        table.notes.insert(0, _keep_best(table, ctx.best, metrics_of("paper")))
        table.caption = caption(what, table.rows, evaluation, unit_of("cross-subject"), folds=sorted(c.folds))
    return table


def _params_m(c: Collector, runs, name: str) -> float | None:
    for r in runs or ():
        if runkeys.N_PARAMS in r.metrics:
            return r.metrics[runkeys.N_PARAMS] / 1e6
    if runs:
        c.warn(f"missing: {name}: no run logged n_params (the Params column)")
    return None


def sota(ctx: ReportContext, evaluation: str) -> Table:
    c = Collector(ctx, "sota", "personalized")
    arch, loss, how = bronchotrack(ctx.index)
    lines = []
    for a, lo in ((arch, loss), OFFSETNET):
        if c.expected is not None and not c.wanted(a, lo):
            c.warn(f"sota: this config has no {a}/{lo} personalized cell, so the {registry.model_name(a, lo)} row "
                   f"is empty")
        line = c.line(a, lo)
        line.extra = [_params_m(c, line.runs, line.model)]
        lines.append(line)
    ours, theirs = lines[0].model, lines[1].model
    table = Table(f"table6-sota-{evaluation}", f"Table 6. State of the art, personalized population, {evaluation} "
                  "evaluation", ("Model",), [Column("Params", "M", highlight=False, decimals=3)]
                  + _metric_columns(metrics_of("paper")),
                  [])
    role = f" in the role of the paper's {registry.model_name(*BRONCHOTRACK)}" if ours != registry.model_name(
        *BRONCHOTRACK) else ""
    what = (f"{ours}{', ' + how + role + ',' if how else role} against {theirs} with its original loss and "
            f"{REFERENCES}, personalized population")
    notes = ["Params: trainable parameters of the trained model, in millions."]
    if evaluation == "accumulated":
        notes.append(PAPER_TABLE6)
    table = _build(ctx, c, table, lines, metrics_of("paper"), evaluation, what, notes)
    if evaluation == "accumulated" and (here := _beside_paper(table, [r for line in lines for r in line.runs],
                                                              ctx.image_size)):
        table.notes.insert(table.notes.index(PAPER_TABLE6) + 1, here)
    return table


# The paper's own Table 6 (accumulated evaluation, its 5 CT patients at 256², both networks from ImageNet): the
# direction a reader compares ours with; its values are not comparable with ours (other data, size and budget)
PAPER_TABLE6 = ("The paper's Table 6, for the direction only (its data, 256² frames, ImageNet start): position L2 "
                "BronchoTrack 4.994 vs OffsetNet 5.694 vox, CE 0.808 vs 0.994 — BronchoTrack better in both.")


# The paper's Table 6 setting, for the differences a reader must know (docs/reproduction.md): its 5 CT patients at
# 256², both backbones from ImageNet
PAPER_SETTING = {"image_size": 256, "patients": 5, "init": "ImageNet"}
INIT_WORDS = {"random": "random", "imagenet": "ImageNet", "file": "a file's"}  # a run's init tag, before any ':'


def _beside_paper(table: Table, runs: Sequence[RunRecord], image_size: int | None) -> str:
    """Our Table 6 in the paper's words: position L2 and CE of the two model rows, which is lower (and whether the
    table finds it significantly so), and every remaining difference from the paper's setting: frame size
    (``image_size``: the config's, which cell runs do not log; None: unknown), patients (those the rows' samples
    rest on), the backbones'
    initialisation (the runs' init tags); numerics, when the rows differ, have a note of their own. Empty without
    both model rows."""
    models = [r for r in table.rows if r.kind == "model"]
    if len(models) != 2:
        return ""
    metrics = metrics_of("paper")
    n_extra = len(table.columns) - len(metrics)
    rows = [table.rows.index(r) for r in models]
    said = []  # (metric's words, its numbers, the lower row's name, significantly)
    for metric, words, unit in (("pos_l2", "position", " vox"), ("ce", "CE", "")):
        j = n_extra + metrics.index(metric)
        vals = [table.rows[i].values[j] for i in rows]
        if any(v is None for v in vals):
            return ""
        a, b = (v.mean for v in vals)
        lower = 0 if a < b else 1
        said.append((words, f"{'position L2' if metric == 'pos_l2' else 'CE'} {models[0].name} {a:.4g} vs "
                     f"{models[1].name} {b:.4g}{unit}", models[lower].name, "best" in table.marks[rows[lower]][j]))
    winners = {w for _, _, w, _ in said}
    verdict = (f"{winners.pop()} lower in both" if len(winners) == 1
               else "; ".join(f"{w} lower in {words}" for words, _, w, _ in said))
    sig = ", ".join(f"{words} {'significantly' if s else 'not significantly'}" for words, _, _, s in said)
    inits = {INIT_WORDS.get(r.tag(TAG_INIT).split(":", 1)[0], "unrecorded") for r in runs}
    paper = PAPER_SETTING
    diffs = [(f"{image_size}² frames" if image_size else "frames of unrecorded size")
             + f" (the paper: {paper['image_size']}²)",
             (f"{len(patients)} patient(s)" if (patients := patients_of(table.rows)) else "patients not known "
              "(no per-trajectory errors)") + f" (the paper: {paper['patients']} CT patients)",
             f"backbones from {inits.pop() if len(inits) == 1 else 'mixed'} weights (the paper: {paper['init']})"]
    return (f"Here: {'; '.join(n for _, n, _, _ in said)} — {verdict} ({sig}: the table's bold). Remaining "
            f"differences from the paper's setting: {', '.join(diffs)}, and the training budget (Source).")


def _profile_values(ctx: ReportContext, c: Collector, arch: str, runs, name: str) -> list[Value]:
    prof = ctx.profile(arch)
    params = _params_m(c, runs, name) if runs else None
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
            f"precision {p.get('precision', '?')}; GMAC: convolution and linear multiply-accumulates per pair.")


def ablation(ctx: ReportContext, evaluation: str) -> Table:
    c = Collector(ctx, "ablation", "personalized")
    lines = []
    for arch in arch_names():
        if not c.has(arch, ABLATION_LOSS):
            continue
        line = c.line(arch, ABLATION_LOSS)
        line.extra = _profile_values(ctx, c, arch, line.runs, line.model)
        lines.append(line)
    columns = [Column("Params", "M", highlight=False, decimals=3),
               Column("Latency", "ms/pair", highlight=False, decimals=2),
               Column("GMAC/pair", highlight=False, decimals=3)] + _metric_columns(metrics_of("ablation"))
    table = Table(f"table7-ablation-{evaluation}", f"Ablation: cost and accuracy per architecture, personalized "
                  f"population, {evaluation} evaluation", ("Network",), columns, [])
    what = (f"Cost and accuracy of each architecture, every one trained with {losses()[ABLATION_LOSS]} (personalized "
            f"population), against {REFERENCES}; only the error columns are judged")
    unmeasured = [col.heading for col in columns[1:3]] if ctx.profiler is None else []
    return _build(ctx, c, table, lines, metrics_of("ablation"), evaluation, what, [_profile_caption(ctx)],
                  unmeasured)


def _thresholds_text(c: Collector, runs) -> str:
    """The thresholds the runs logged (eval.* params; metrics on runs logged before); a warning when they differ."""
    position, position_mm, angle, gap = EVAL_PARAMS  # params (runs.views)
    names = {position: "{:g} voxels", position_mm: "{:g} mm", angle: "{:g}°", gap: "{:g} frames"}
    seen = {k: sorted({v for r in runs if (v := r.setting(k)) is not None}) for k in names}
    if not any(seen.values()):
        return ("CTF: share of the frames after the given first one tracked within the position and angle "
                "thresholds (not logged by these runs); ATE: RMSE of the position error over every frame; RPE: "
                "RMSE of the relative-motion error over a frame gap; drift: final position error / path length.")
    for k, values in seen.items():
        if len(values) > 1:
            c.warn(f"tracking: the runs used different {k} ({', '.join(f'{v:g}' for v in values)}); their CTF/RPE "
                   f"are not comparable")
    text = {k: "/".join(fmt.format(v) for v in seen[k]) or "?" for k, fmt in names.items()}
    return (f"CTF: share of the frames after the given first one with position error below "
            f"{text[position_mm]} (CTF mm) or {text[position]} (CTF vox) and rotation error "
            f"below {text[angle]}; ATE: RMSE of the position error over every frame, unaligned; RPE: RMSE "
            f"of the relative-motion error over {text[gap]} (trajectories shorter than that have none); "
            f"drift: final position error / ground-truth path length.")


def tracking(ctx: ReportContext, evaluation: str) -> Table:
    """The literature's camera-tracking metrics (the paper's Table 1 and the visual-odometry benchmarks)."""
    del evaluation  # whole-trajectory metrics: one table
    c = Collector(ctx, "tracking", "personalized")
    lines = [c.line(arch, loss, grouped=True) for arch in arch_names() for loss in losses() if c.has(arch, loss)]
    every = [r for line in lines for r in line.runs]
    order = tracking_order(every)
    table = Table("table9-tracking", "Table 9. Camera tracking: CTF, ATE, RPE and drift, personalized population",
                  ("Network", "Loss"), _metric_columns(order), [])
    what = f"Camera-tracking metrics of each network and loss against {REFERENCES}, personalized population"
    return _build(ctx, c, table, lines, order, "trajectory", what, [_thresholds_text(c, every)])


def tracking_order(runs: Sequence[RunRecord]) -> list[str]:
    """The tracking columns: mm first where the runs know the voxel spacing (a finite ``traj.ctf_mm.mean``),
    voxels first where none does (e.g. imported poses without spacing)."""
    known = any(math.isfinite(r.metrics.get(runkeys.metric("ctf_mm", "traj"), math.nan)) for r in runs)
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
