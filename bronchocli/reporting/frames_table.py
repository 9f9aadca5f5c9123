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

from .aggregate import model_sample, replicates
from .collect import FRAME, LOSS, POP
from .context import EVAL_TEXT, LOSSES, Collector, NoData, ReportContext, arch_names, budget_text, finish, init_text
from .judge import better_reference, metric_rows
from .stats import derived, holm
from .table_model import Column, Estimate, Row, Table, Value

FRAMES = ("world", "camera")
FRAME_METRICS = {"pos_l2": "Position", "rot_l2": "Rotation"}


def _population(ctx: ReportContext) -> str:
    pops = {i[POP] for i in ctx.index.runs if i[FRAME] in FRAMES}
    return "personalized" if "personalized" in pops else "cross-subject"


def _frame_skill(row_w, ref_w, row_c, ref_c, s) -> tuple[Estimate, Estimate, float]:
    w = derived([row_w, ref_w], lambda m, r: 1.0 - m / r, s.level)
    c = derived([row_c, ref_c], lambda m, r: 1.0 - m / r, s.level)
    diff = derived([row_w, ref_w, row_c, ref_c], lambda a, b, c_, d: (1.0 - a / b) - (1.0 - c_ / d), s.level)
    return Estimate(w.value, w.lo, w.hi), Estimate(c.value, c.lo, c.hi), diff.p


def frames(ctx: ReportContext, evaluation: str) -> Table:
    have = {i[FRAME] for i in ctx.index.runs}
    if not set(FRAMES) <= have:
        raise NoData(f"frames table skipped: the runs have pose frame(s) {', '.join(sorted(have)) or 'none'}, "
                     f"not both world and camera")
    population = _population(ctx)
    metrics = list(FRAME_METRICS)
    per_frame = {}
    collectors = {}
    for frame in FRAMES:
        c = Collector(ctx, "frames", population, frame=frame)
        archs, losses = c.combos()
        losses = [lo for lo in LOSSES if lo in losses and any(i[LOSS] == lo and i[FRAME] == frame
                                                                for i in ctx.index.runs)]
        lines = [c.line(name, LOSSES[lo], a, lo) for a, name in arch_names().items() if a in archs for lo in losses]
        lines = [ln for ln in lines if ln.runs]
        every = [r for ln in lines for r in ln.runs]
        built = metric_rows(lines, ctx.frames(every), metrics, evaluation, grouped=False, settings=ctx.settings)
        per_frame[frame] = ({(ln.group, ln.label): ln for ln in lines}, built)
        collectors[frame] = c
    both = [k for k in per_frame["world"][0] if k in per_frame["camera"][0]]
    if not both:
        raise NoData("frames table skipped: no architecture/loss has FINISHED runs in both pose frames")
    several_losses = len({k[1] for k in both}) > 1
    s = ctx.settings
    cells: dict[tuple, list] = {k: [] for k in both}
    raw: dict[str, list[float]] = {m: [] for m in metrics}
    for j, m in enumerate(metrics):
        refs = {f: better_reference(per_frame[f][1].references, j) for f in FRAMES}
        for k in both:
            samples = {f: model_sample(replicates(per_frame[f][0][k].runs), ctx.frames(per_frame[f][0][k].runs),
                                       evaluation, m) for f in FRAMES}
            if any(x is None for x in (*samples.values(), *refs.values())):
                cells[k] += [None, None]
                raw[m].append(float("nan"))
                continue
            try:
                w, c, p = _frame_skill(samples["world"], refs["world"], samples["camera"], refs["camera"], s)
            except ValueError:  # the frames share no test trajectory
                cells[k] += [None, None]
                raw[m].append(float("nan"))
                continue
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
        arch_name, loss_name = k
        label = f"{arch_name} ({loss_name})" if several_losses else arch_name
        runs = per_frame["world"][0][k].runs + per_frame["camera"][0][k].runs
        rows.append(Row("", label, values, [r.run_id for r in runs]))
    columns = []
    for m, name in FRAME_METRICS.items():
        columns += [Column(f"{name} skill, world", highlight=False), Column(f"{name} skill, camera", highlight=False),
                    Column(f"{name} p", highlight=False)]
    table = Table(f"table8-frames-{evaluation}", f"Table 8. Pose-frame convention: skill with world vs camera "
                  f"labels, {population} population, {evaluation} evaluation", ("Model",), columns, rows)
    every = [r for f in FRAMES for ln in per_frame[f][0].values() for r in ln.runs]
    table.caption = " ".join([
        f"{EVAL_TEXT[evaluation]}.",
        "Skill = 1 − error / error of the better image-blind reference (zero motion or training mean) of the same "
        "pose frame, on the same test trajectories: 0 = no better than an image-blind model, 1 = perfect; higher is "
        "better. Cells: skill [95% interval: delta-method t interval, variance components over seeds and test "
        "trajectories, Satterthwaite df]. p: t test of equal skill in the two frames (the test trajectories "
        "shared by both frames and their references, seeds independent; delta method, two-sided), "
        f"Holm-corrected over the rows of each metric; significant when < {s.alpha:g}.",
        budget_text(every),
        init_text(every),
        f"Sweep '{ctx.index.sweep}' (MLflow experiment '{ctx.index.experiment}').",
    ])
    merged = collectors["world"]
    merged.lacking += collectors["camera"].lacking
    merged.warnings += [w for w in collectors["camera"].warnings if w not in merged.warnings]
    return finish(table, merged)
