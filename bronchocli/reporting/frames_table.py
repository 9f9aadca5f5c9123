"""The frame-convention table: does the model learn more from world or from camera-frame labels?

Errors in the ``world`` and ``camera`` parameterisations are not comparable
(different targets), so each frame is judged against its own image-blind
references: skill = 1 - error / error of the better reference *of that frame*
(on the same test trajectories). Rows are the architectures (x loss when the
runs have several), columns the skill of each frame for position and rotation
L2 and the p of their difference: a delta-method t test on the variance
components of the four cells (the test trajectories are shared by the two
frames and their references, seeds independent; stats.derived),
Holm-corrected over the rows of each metric.
"""

from __future__ import annotations

import math

from .. import registry
from .aggregate import model_sample, replicates
from .captions import ERRORS, budget_text, caption, dataset_text, fixed_seeds_note, init_text, seeds_phrase
from .collect import FRAME, LOSS, POP
from .context import Collector, NoData, ReportContext, arch_names, finish, losses, metrics_of
from .estimand import unit_of
from .judge import judged, metric_rows
from .stats import Sample, common_keys, derived, holm, skill
from .table_model import Column, Estimate, Row, Table, Value

FRAMES = ("world", "camera")


def _population(ctx: ReportContext) -> str:
    pops = {i[POP] for i in ctx.index.runs if i[FRAME] in FRAMES}
    return "personalized" if "personalized" in pops else "cross-subject"


def _frame_skill(row_w, ref_w, row_c, ref_c, s) -> tuple[Estimate, Estimate, float]:
    w = skill(row_w, ref_w, s.level)
    c = skill(row_c, ref_c, s.level)
    diff = derived([row_w, ref_w, row_c, ref_c], lambda a, b, c_, d: (1.0 - a / b) - (1.0 - c_ / d), s.level)
    return Estimate(w.value, w.lo, w.hi), Estimate(c.value, c.lo, c.hi), diff.p


def _better(refs: dict[str, list], j: int) -> Sample | None:
    """The reference with the lower mean of metric ``j`` (judged or not: a refused one still gives means)."""
    found = [x[j] for x in refs.values() if x[j] is not None]
    return min(found, key=lambda x: x.mean) if found else None


def _point_skill(model: Sample, ref: Sample) -> Estimate:
    keys = common_keys([model, ref])
    return Estimate(1.0 - model.restricted(keys).mean / ref.restricted(keys).mean)


def _row_cells(samples: dict[str, Sample | None], refs: dict[str, Sample | None], s
               ) -> tuple[Estimate | None, Estimate | None, float]:
    """World skill, camera skill and the p of their difference for one row: means only (p NaN) when a sample
    is refused (stats.refusal: 2 seeds, too few patients); nothing without data or shared trajectories."""
    every = (*samples.values(), *refs.values())
    if any(x is None for x in every):
        return None, None, math.nan
    try:
        if any(judged(x) is None for x in every):
            return _point_skill(samples["world"], refs["world"]), _point_skill(samples["camera"], refs["camera"]), \
                math.nan
        return _frame_skill(samples["world"], refs["world"], samples["camera"], refs["camera"], s)
    except ValueError:  # the frames share no test trajectory
        return None, None, math.nan


def frames(ctx: ReportContext, evaluation: str) -> Table:
    have = {i[FRAME] for i in ctx.index.runs}
    if not set(FRAMES) <= have:
        raise NoData(f"frames table skipped: the runs have pose frame(s) {', '.join(sorted(have)) or 'none'}, "
                     f"not both world and camera")
    population = _population(ctx)
    unit = unit_of(population)
    metrics = metrics_of("frames")
    per_frame = {}
    collectors = {}
    for frame in FRAMES:
        c = Collector(ctx, "frames", population, frame=frame)
        archs, used = c.combos()
        labels = losses()
        used = [lo for lo in labels if lo in used and any(i[LOSS] == lo and i[FRAME] == frame
                                                          for i in ctx.index.runs)]
        lines = [c.line(a, lo, grouped=True) for a in arch_names() if a in archs for lo in used]
        lines = [ln for ln in lines if ln.runs]
        every = [r for ln in lines for r in ln.runs]
        built = metric_rows(lines, ctx.frames(every), metrics, evaluation, grouped=False, settings=ctx.settings,
                            unit=unit)
        per_frame[frame] = ({(ln.group, ln.label): ln for ln in lines}, built)
        collectors[frame] = c
    both = [k for k in per_frame["world"][0] if k in per_frame["camera"][0]]
    if not both:
        raise NoData("frames table skipped: no architecture/loss has FINISHED runs in both pose frames")
    s = ctx.settings
    cells: dict[tuple, list] = {k: [] for k in both}
    raw: dict[str, list[float]] = {m: [] for m in metrics}
    for j, m in enumerate(metrics):
        refs = {f: _better(per_frame[f][1].references, j) for f in FRAMES}
        for k in both:
            samples = {f: model_sample(replicates(per_frame[f][0][k].runs), ctx.frames(per_frame[f][0][k].runs),
                                       evaluation, m, unit=unit) for f in FRAMES}
            w, c, p = _row_cells(samples, refs, s)
            cells[k] += [w, c]
            raw[m].append(p)
    adjusted = {}
    for m in metrics:
        ok = [i for i, p in enumerate(raw[m]) if p == p]
        adj = holm([raw[m][i] for i in ok]) if ok else []
        adjusted[m] = {i: a for i, a in zip(ok, adj)}
    rows = []
    for i, k in enumerate(both):
        values: list[Value] = []
        for j, m in enumerate(metrics):
            values += cells[k][2 * j: 2 * j + 2]
            a = adjusted[m].get(i)
            values.append("—" if a is None else f"{a:.3f}" + (" (significant)" if a < s.alpha else ""))
        line = per_frame["world"][0][k]
        runs = line.runs + per_frame["camera"][0][k].runs
        rows.append(Row("", line.model, values, [r.run_id for r in runs], model=line.model))
    columns = []
    for m in metrics:
        spec = registry.metric(m)
        name = spec.short_label or spec.label
        columns += [Column(f"{name} skill, world", highlight=False), Column(f"{name} skill, camera", highlight=False),
                    Column(f"{name} p", highlight=False)]
    table = Table(f"table8-frames-{evaluation}", f"Table 8. Pose-frame convention: skill with world vs camera "
                  f"labels, {population} population, {evaluation} evaluation", ("Model",), columns, rows)
    every = [r for f in FRAMES for ln in per_frame[f][0].values() for r in ln.runs]
    built_rows = [r for f in FRAMES for r in per_frame[f][1].rows]
    what = ("Skill of each architecture trained with world labels (the paper's Euler differences) vs camera labels "
            f"(SE(3) in the previous camera's frame), {population} population")
    cell = (f"skill = 1 − error / error of the better image-blind reference of the same frame, from "
            f"{ERRORS[evaluation]}, mean over {seeds_phrase(built_rows)}")
    table.caption = caption(what, built_rows, evaluation, unit, cell=cell,
                            direction="skill: 0 = no better than an image-blind model, 1 = perfect")
    table.notes = [n for n in (
        f"p: test of equal skill in the two frames (same test trajectories, seeds independent), Holm-corrected over "
        f"the rows of each metric; significant when < {s.alpha:g}.",
        fixed_seeds_note(built_rows)) if n]
    table.source = [p for p in (f"Sweep '{ctx.index.sweep}' (MLflow experiment '{ctx.index.experiment}').",
                                budget_text(every), init_text(every), dataset_text(every)) if p]
    merged = collectors["world"]
    merged.lacking += collectors["camera"].lacking
    merged.warnings += [w for w in collectors["camera"].warnings if w not in merged.warnings]
    return finish(table, merged)
