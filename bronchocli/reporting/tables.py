"""The paper's tables built from a sweep's runs: a name -> builder registry.

``TABLES[name](ctx, evaluation)`` returns a ``model.Table``; ``evaluation`` is
``accumulated`` or ``pair``. What each table holds and how it is aggregated is
documented in docs/reports.md; in short:

* ``personalized`` (Tables 2/3): 4 BronchoPose architectures x 3 rotation
  losses, personalized runs, pooled over seeds when there are several;
* ``cross-subject`` (Tables 4/5): the same combinations, pooled over the test
  pairs/trajectories of every held-out patient (``aggregate.pooled``);
  ``ctx.best`` > 0 keeps the best N combinations by mean rank over the metrics;
* ``sota`` (Table 6): BronchoTrack (ConvLSTM + MSE+CE) vs OffsetNet trained
  with MSE+MSE (its original loss), personalized, with parameter counts;
* ``ablation``: params, latency and GMAC per architecture (from
  ``profiling.profile_arch`` through ``ctx.profiler``) next to position L2 and
  CE of its MSE+CE personalized run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

from ..errors import BronchoError
from ..metrics import Stat
from .aggregate import NOUN, PREFIX, CellValue, cell_value
from .collect import RunIndex, RunRecord
from .layout import Column, Row, Table, Value, missing_cells

ARCH_GROUPS = {"baseline": "Baseline", "lstm": "+LSTM", "conv3d": "+3D", "convlstm": "+ConvRNN"}
ARCH_NAMES = {**ARCH_GROUPS, "offsetnet": "OffsetNet"}
LOSSES = {"mse": "MSE+MSE", "de": "MSE+DE", "ce": "MSE+CE"}
METRICS = {"pos_l2": ("Position L2", "vox"), "rot_l2": ("Rotation L2", "°"), "de": ("DE", "rad"), "ce": ("CE", "")}
BRONCHOTRACK = ("convlstm", "ce")
OFFSETNET = ("offsetnet", "mse")  # OffsetNet's own loss (Sganga et al.): MSE on position and rotation
ABLATION_LOSS = "ce"  # every architecture with BronchoTrack's loss, so the rows differ in architecture only
UNITS = "Units: position L2 in voxels, rotation L2 in degrees, DE in radians, CE unitless; lower is better."
EVAL_TEXT = {
    "accumulated": "Accumulated evaluation: the predicted relative poses of each test trajectory are chained from "
                   "its true first pose and only the last pose is scored",
    "pair": "Per-pair evaluation: the error of each predicted relative pose between consecutive frames",
}
NUMBERS = {("personalized", "accumulated"): 2, ("personalized", "pair"): 3,
           ("cross-subject", "accumulated"): 4, ("cross-subject", "pair"): 5}

Profiler = Callable[[str], Mapping[str, Any]]


@dataclass
class ReportContext:
    """Inputs shared by the table builders."""

    index: RunIndex
    best: int = 0  # cross-subject: keep the best N combinations (0 = all)
    profiler: Profiler | None = None  # arch -> profiling.profile_arch's dict; None: no latency/GMAC
    profiler_note: str = ""  # why there is no profiler, for the caption
    _profiles: dict[str, Mapping[str, Any] | None] = field(default_factory=dict)

    def profile(self, arch: str) -> Mapping[str, Any] | None:
        if self.profiler is None:
            return None
        if arch not in self._profiles:
            self._profiles[arch] = self.profiler(arch)
        return self._profiles[arch]


class _Collector:
    """Finds the runs of each table row and gathers the warnings that go with them."""

    def __init__(self, ctx: ReportContext, population: str):
        self.index, self.population = ctx.index, population
        self.expected = ctx.index.replicas(population)
        self.warnings: list[str] = []

    def warn(self, text: str) -> None:
        if text not in self.warnings:
            self.warnings.append(text)

    def runs(self, arch: str, loss: str) -> list[RunRecord] | None:
        name = f"{self.population} {arch} {LOSSES[loss]}"
        runs = self.index.select(self.population, arch, loss)
        if not runs:
            others = self.index.not_finished(self.population, arch, loss)
            why = "; ".join(f"{r.run_id} {r.status}" + (f" ({r.tag('failure_reason')})" if r.tag("failure_reason")
                                                        else "") for r in others)
            self.warn(f"missing: {name}: no FINISHED run" + (f" ({why})" if why else ""))
            return None
        have = {(r.tag("fold"), r.tag("seed")) for r in runs}
        lacking = [f"fold {f or '-'} seed {s}" for f, s in self.expected if (f, s) not in have]
        if lacking:
            self.warn(f"missing: {name}: no FINISHED run for {', '.join(lacking)} (cell left empty, not pooled "
                      f"over fewer runs)")
            return None
        for r in runs:
            dropped = self.index.duplicates.get(r.identity)
            if dropped:
                self.warn(f"duplicate: {r.label} has {len(dropped) + 1} FINISHED runs; using the latest {r.run_id}, "
                          f"ignoring {', '.join(d.run_id for d in dropped)}")
        return runs

    def value(self, runs: Sequence[RunRecord] | None, metric: str, evaluation: str) -> Value:
        if runs is None:
            return None
        cell: CellValue = cell_value(runs, metric, evaluation)
        if cell.stat is None:
            self.warn(f"missing: {cell.problem}")
        return cell.stat


def _metric_columns(names: Sequence[str] = tuple(METRICS)) -> list[Column]:
    return [Column(*METRICS[m]) for m in names]


def _n_text(table: Table, evaluation: str) -> str:
    ns = sorted({v.n for r in table.rows for v in r.values if isinstance(v, Stat) and v.n > 0})
    if not ns:
        return f"the {NOUN[evaluation]}"
    span = str(ns[0]) if len(ns) == 1 else f"{ns[0]}–{ns[-1]}"
    return f"{span} {NOUN[evaluation]} per cell"


def _provenance(ctx: ReportContext, c: _Collector) -> str:
    seeds = sorted({s for _, s in c.expected}, key=lambda s: (len(s), s))
    text = f"Sweep '{ctx.index.sweep}' (MLflow experiment '{ctx.index.experiment}'), pose frame " \
           f"'{ctx.index.pose_frame}', seed{'s' if len(seeds) > 1 else ''} {', '.join(seeds) or '-'}"
    if len(seeds) > 1:
        text += " (pooled like folds)"
    return text + "; the MLflow run ids are listed with the table."


def _caption(ctx: ReportContext, c: _Collector, table: Table, evaluation: str, extra: str = "") -> str:
    parts = [f"{EVAL_TEXT[evaluation]}. Mean ± population std (ddof=0) over {_n_text(table, evaluation)}."]
    if extra:
        parts.append(extra)
    parts += [UNITS, _provenance(ctx, c)]
    return " ".join(parts)


def _finish(table: Table, c: _Collector, expected_empty: Sequence[str] = ()) -> Table:
    """Attach the warnings; columns in ``expected_empty`` (left empty on purpose) are not reported."""
    table.warnings = list(c.warnings)
    empty = missing_cells(table, expected_empty)
    if empty:
        table.warnings.append(f"{table.key}: {len(empty)} row(s) with empty cells shown as —: {'; '.join(empty)}")
    return table


def _grid_rows(c: _Collector, evaluation: str) -> list[Row]:
    """The paper's architecture x loss layout, restricted to what the sweep ran (any status)."""
    rows = []
    for arch, group in ARCH_GROUPS.items():
        if arch not in c.index.archs:
            continue
        for loss, label in LOSSES.items():
            if loss not in c.index.losses:
                continue
            runs = c.runs(arch, loss)
            rows.append(Row(group, label, [c.value(runs, m, evaluation) for m in METRICS],
                            [r.run_id for r in runs or ()]))
    return rows


def personalized(ctx: ReportContext, evaluation: str) -> Table:
    c = _Collector(ctx, "personalized")
    n = NUMBERS[("personalized", evaluation)]
    table = Table(f"table{n}-personalized-{evaluation}", f"Table {n}. Personalized population, {evaluation} "
                  "evaluation", ("Network", "Loss"), _metric_columns(), _grid_rows(c, evaluation))
    table.caption = _caption(ctx, c, table, evaluation)
    return _finish(table, c)


def _mean_rank(rows: Sequence[Row]) -> list[float]:
    """Per row, the mean over metric columns of its rank (1 = lowest mean; ties share the average rank)."""
    ranks = [0.0] * len(rows)
    for j in range(len(METRICS)):
        means = [r.values[j].mean for r in rows]  # type: ignore[union-attr]
        for i, m in enumerate(means):
            ranks[i] += sum(x < m for x in means) + (sum(x == m for x in means) + 1) / 2
    return [r / len(METRICS) for r in ranks]


def _keep_best(rows: list[Row], best: int) -> tuple[list[Row], str]:
    complete = [r for r in rows if all(v is not None and not math.isnan(v.mean) for v in r.values)]  # type: ignore
    ranks = dict(zip(map(id, complete), _mean_rank(complete)))
    chosen = sorted(complete, key=lambda r: (ranks[id(r)], r.values[0].mean))[:best]  # type: ignore[union-attr]
    keep = {id(r) for r in chosen}
    note = (f"Showing the best {len(chosen)} of {len(complete)} complete network/loss combinations, ranked by the "
            f"mean of their ranks over the four metric means.")
    return [r for r in rows if id(r) in keep], note


def cross_subject(ctx: ReportContext, evaluation: str) -> Table:
    c = _Collector(ctx, "cross-subject")
    n = NUMBERS[("cross-subject", evaluation)]
    rows = _grid_rows(c, evaluation)
    note = ""
    if ctx.best > 0:
        rows, note = _keep_best(rows, ctx.best)
    folds = sorted({f for f, _ in c.expected})
    pooled = (f"Leave-one-patient-out over {len(folds)} fold(s) (held-out patients: {', '.join(folds) or '-'}); each "
              f"cell pools the {NOUN[evaluation]} of all held-out patients: pooled mean = n-weighted mean of the "
              f"runs' means, pooled std = population std of the union, exact from each run's mean, std and n "
              f"(sqrt(Σn(σ²+μ²)/N − μ²)).")
    table = Table(f"table{n}-cross-subject-{evaluation}", f"Table {n}. Cross-subject population, {evaluation} "
                  "evaluation", ("Network", "Loss"), _metric_columns(), rows)
    table.caption = _caption(ctx, c, table, evaluation, " ".join(x for x in (pooled, note) if x))
    return _finish(table, c)


def _params_m(c: _Collector, runs: Sequence[RunRecord] | None, name: str) -> float | None:
    for r in runs or ():
        if "n_params" in r.metrics:
            return r.metrics["n_params"] / 1e6
    if runs:
        c.warn(f"missing: {name}: no run logged n_params")
    return None


def sota(ctx: ReportContext, evaluation: str) -> Table:
    c = _Collector(ctx, "personalized")
    rows = []
    for (arch, loss), name in ((BRONCHOTRACK, "BronchoTrack (ConvLSTM, MSE+CE)"),
                               (OFFSETNET, "OffsetNet (MSE+MSE)")):
        runs = c.runs(arch, loss)
        values: list[Value] = [_params_m(c, runs, name)] + [c.value(runs, m, evaluation) for m in METRICS]
        rows.append(Row("", name, values, [r.run_id for r in runs or ()]))
    columns = [Column("Params", "M", highlight=False, decimals=3)] + _metric_columns()
    table = Table(f"table6-sota-{evaluation}", f"Table 6. State of the art, personalized population, {evaluation} "
                  "evaluation", ("Model",), columns, rows)
    extra = ("BronchoTrack is ConvLSTM trained with MSE+CE; OffsetNet is trained with MSE on position and rotation, "
             "its original loss. Params: trainable parameters of the trained model (n_params), millions.")
    table.caption = _caption(ctx, c, table, evaluation, extra)
    return _finish(table, c)


def _profile_values(ctx: ReportContext, c: _Collector, arch: str, runs) -> list[Value]:
    prof = ctx.profile(arch)
    params = _params_m(c, runs, ARCH_NAMES[arch]) if runs else None
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
    c = _Collector(ctx, "personalized")
    rows = []
    for arch, name in ARCH_NAMES.items():
        if arch not in c.index.archs:
            continue
        runs = c.runs(arch, ABLATION_LOSS)
        values = _profile_values(ctx, c, arch, runs) + [c.value(runs, m, evaluation) for m in ("pos_l2", "ce")]
        rows.append(Row("", name, values, [r.run_id for r in runs or ()]))
    columns = [Column("Params", "M", highlight=False, decimals=3),
               Column("Latency", "ms/pair", highlight=False, decimals=2),
               Column("GMAC/pair", highlight=False, decimals=3)] + _metric_columns(("pos_l2", "ce"))
    table = Table(f"table7-ablation-{evaluation}", f"Ablation: cost and accuracy per architecture, personalized "
                  f"population, {evaluation} evaluation", ("Network",), columns, rows)
    extra = (f"Every architecture trained with {LOSSES[ABLATION_LOSS]}; only the error columns are ranked. "
             + _profile_caption(ctx))
    table.caption = _caption(ctx, c, table, evaluation, extra)
    unmeasured = [col.heading for col in columns[1:3]] if ctx.profiler is None else []
    return _finish(table, c, unmeasured)


TABLES: dict[str, Callable[[ReportContext, str], Table]] = {
    "personalized": personalized,
    "cross-subject": cross_subject,
    "sota": sota,
    "ablation": ablation,
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
        return list(PREFIX)
    if name not in PREFIX:
        raise BronchoError(f"--eval {name!r}: must be one of accumulated, pair, both")
    return [name]
