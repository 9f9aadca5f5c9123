"""What every table builder shares: the report context, the per-table run finder, caption pieces.

``ReportContext`` holds the run index, the loader of each run's
``trajectory_errors.csv`` (cached), the statistical settings and the profiler
of the ablation table. ``Collector`` finds the runs of each table row — the
config's cells of the table's stage (config mode) or every (fold, seed) the
sweep has (sweep mode) — keeps complete replicates only, and remembers which
cells the table lacks, for one warning line per table.
"""

from __future__ import annotations

from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

from .. import registry
from ..runs.records import TAG_INIT
from .aggregate import Frames
from .collect import FOLD, SEED, Identity, RunIndex, RunRecord, identity_label, seed_key, stop_reasons
from .judge import Line, Settings
from .table_model import Row, Table, missing_cells

BRONCHOTRACK = ("convlstm", "ce")  # the paper's BronchoTrack, when no sota stage selected one
OFFSETNET = ("offsetnet", "mse")  # OffsetNet's own loss (Sganga et al.): MSE on position and rotation
ABLATION_LOSS = "ce"  # every architecture with BronchoTrack's loss, so the rows differ in architecture only
EVAL_TEXT = {
    "accumulated": "Accumulated evaluation: the predicted relative poses of each test trajectory are chained from "
                   "its true first pose and only the last pose is scored",
    "pair": "Per-pair evaluation: the error of each predicted relative pose between consecutive frames",
    "trajectory": "Camera tracking: the predicted relative poses of each test trajectory are chained from its true "
                  "first pose and every frame is scored (per trajectory, then mean over trajectories)",
}


def losses() -> dict[str, str]:
    """Rotation loss -> its row label, in registration order, the paper's first (registry.py, read at each call:
    a registered loss has rows too)."""
    return {name: registry.rot_loss(name).label for name in registry.rot_loss_names()}


def metrics_of(table: str) -> list[str]:
    """The metrics a report table group shows ("paper", "ablation", "skill", "frames", "tracking"), in column
    order (registry.py, read at each call: a registered metric is a column too)."""
    return list(registry.metric_names(table=table))


def heading(metric: str) -> tuple[str, str]:
    """A metric's column heading and the unit shown under it: ("Position L2", "vox")."""
    spec = registry.metric(metric)
    return spec.label, spec.symbol


def _prose(label: str) -> str:
    """A label inside a sentence: "Position L2" -> "position L2"; an acronym ("DE") stays as it is."""
    return label[0].lower() + label[1:] if label[1:2].islower() else label


def units_text(table: str = "paper") -> str:
    """The caption's units of a table group's metrics: "Units: position L2 in voxels, ..., CE unitless; lower is
    better." (the direction of each, from registry.py)."""
    specs = registry.metric_specs(table=table)
    parts = [f"{_prose(s.label)} {s.unit}" if s.unit == "unitless" else f"{_prose(s.label)} in {s.unit}"
             for s in specs]
    higher = [s.label for s in specs if s.higher_is_better]
    direction = "lower is better" + (f" except {', '.join(higher)} (higher is better)" if higher else "")
    return f"Units: {', '.join(parts)}; {direction}."


def arch_names(paper_tables: bool = False) -> dict[str, str]:
    """Architecture -> its row label, in the tables' row order (registry.py, read at each call: a registered
    architecture has rows too). ``paper_tables``: only the row groups of the personalized/cross-subject tables."""
    return {s.name: s.label for s in registry.table_order() if s.paper_tables or not paper_tables}


def model_name(arch: str) -> str:
    """The architecture's name in prose ("ConvLSTM"); an unregistered one (an old run's tag) as it is."""
    return registry.arch(arch).model_name if arch in registry.arch_names() else arch


Profiler = Callable[[str], Mapping[str, Any]]
Loader = Callable[[RunRecord], Any]  # run -> its trajectory_errors table (aggregate.read_errors) or None


class NoData(Exception):
    """A table that does not apply to these runs (e.g. the frames table with one pose frame)."""


@dataclass
class ReportContext:
    """Inputs shared by the table builders."""

    index: RunIndex
    best: int = 0  # cross-subject: keep the best N combinations (0 = all)
    profiler: Profiler | None = None  # arch -> models.profile.profile_arch's dict; None: no latency/GMAC
    profiler_note: str = ""  # why there is no profiler, for the caption
    errors: Loader | None = None  # run -> trajectory_errors table; None: logged means only
    history: Callable[[str, str], Any] | None = None  # (run id, metric) -> [(step, value)]: fig-training-curves
    settings: Settings = field(default_factory=Settings)
    default_train_trajectories: int | None = None  # what train_trajectories "" means (config's splits.train)
    _profiles: dict[str, Mapping[str, Any] | None] = field(default_factory=dict)
    _frames: dict[str, Any] = field(default_factory=dict)

    def profile(self, arch: str) -> Mapping[str, Any] | None:
        if self.profiler is None:
            return None
        if arch not in self._profiles:
            self._profiles[arch] = self.profiler(arch)
        return self._profiles[arch]

    def frames(self, runs: Sequence[RunRecord]) -> Frames:
        """Each run's trajectory errors (loaded once per run; several at a time, for remote artifact stores)."""
        todo = list({r.run_id: r for r in runs if r.run_id not in self._frames}.values())
        if todo and self.errors is not None:
            with ThreadPoolExecutor(max_workers=min(8, len(todo))) as pool:
                for r, errors in zip(todo, pool.map(self.errors, todo)):
                    self._frames[r.run_id] = errors
        for r in todo:
            self._frames.setdefault(r.run_id, None)
        return {r.run_id: self._frames[r.run_id] for r in runs}


def bronchotrack(index: RunIndex) -> tuple[str, str, str]:
    """(arch, rot_loss, how chosen) of BronchoTrack: the sota stage's top-1 selection, else ConvLSTM + MSE+CE."""
    sel = index.selections.get("sota")
    if sel and sel.get("selected"):
        first = sel["selected"][0]
        arch, loss = first.get("arch", BRONCHOTRACK[0]), first.get("rot_loss", BRONCHOTRACK[1])
        by = sel.get("by") or "a validation metric"
        return arch, loss, f"BronchoTrack is the sota stage's selection (top 1 by {by}, validation)"
    return (*BRONCHOTRACK, "BronchoTrack is ConvLSTM trained with MSE+CE (the paper's)")


class Collector:
    """Finds the runs of each row of one table and gathers the warnings that go with them."""

    def __init__(self, ctx: ReportContext, table: str, population: str, frame: str | None = None,
                 size: str | None = None):
        self.ctx, self.index, self.table, self.population = ctx, ctx.index, table, population
        self.frame = ctx.index.pose_frame if frame is None else frame
        self.size = ctx.index.train_size if size is None else size
        self.expected = ctx.index.expected(table, population, self.frame, self.size)
        self.replicas = ctx.index.replicas(population, self.frame, self.size)
        self.lacking: list[str] = []
        self.warnings: list[str] = []
        self.seeds: set[str] = set()
        self.folds: set[str] = set()

    def warn(self, text: str) -> None:
        if text not in self.warnings:
            self.warnings.append(text)

    def combos(self) -> tuple[list[str], list[str]]:
        """The architectures and losses of the table's rows: the config's cells (config mode) or any run."""
        if self.expected is not None:
            return sorted({i[0] for i in self.expected}), sorted({i[1] for i in self.expected})
        return sorted(self.index.archs), sorted(self.index.losses)

    def has(self, arch: str, loss: str) -> bool:
        """Whether the table has a row for (arch, loss): a config cell (config mode) or any run of both."""
        if self.expected is not None:
            return any(i[0] == arch and i[1] == loss for i in self.expected)
        return arch in self.index.archs and loss in self.index.losses

    def wanted(self, arch: str, loss: str) -> list[Identity]:
        if self.expected is not None:
            return [i for i in self.expected if i[0] == arch and i[1] == loss]
        return [(arch, loss, self.population, f, s, self.frame, self.size) for f, s in self.replicas]

    def _lack(self, ident: Identity) -> None:
        why = "; ".join(f"{r.status}" + (f": {r.tag('failure_reason')}" if r.tag("failure_reason") else "")
                        + f" {r.run_id}" for r in self.index.not_finished(ident))
        self.lacking.append(identity_label(ident) + (f" ({why})" if why else ""))

    def runs(self, arch: str, loss: str) -> list[RunRecord]:
        """The row's runs, complete replicates only (a seed missing a fold is dropped); lacking cells noted."""
        wanted = self.wanted(arch, loss)
        have = {r.identity: r for r in self.index.select(self.population, arch, loss, self.frame, self.size)}
        for ident in wanted:
            if ident not in have:
                self._lack(ident)
        by_seed: dict[str, list[Identity]] = {}
        for ident in wanted:
            by_seed.setdefault(ident[SEED], []).append(ident)
        out = []
        for seed in sorted(by_seed, key=seed_key):
            idents = by_seed[seed]
            if all(i in have for i in idents):
                out += [have[i] for i in idents]
                self.seeds.add(seed)
                self.folds |= {i[FOLD] for i in idents if i[FOLD]}
        for r in out:
            dropped = self.index.duplicates.get(r.identity)
            if dropped:
                self.warn(f"duplicate: {r.label} has {len(dropped) + 1} FINISHED runs; using the latest {r.run_id}, "
                          f"ignoring {', '.join(d.run_id for d in dropped)}")
        return out

    def line(self, group: str, label: str, arch: str, loss: str, extra: Sequence = ()) -> Line:
        return Line(group, label, self.runs(arch, loss), list(extra))


def _span(values: Sequence[float], fmt: str = "{:,.0f}") -> str:
    lo, hi = min(values), max(values)
    return fmt.format(lo) if lo == hi else f"{fmt.format(lo)}–{fmt.format(hi)}"


def n_text(rows: Sequence[Row], evaluation: str, folds: Sequence[str] = ()) -> str:
    """'n per cell = 2 seeds × 12 test trajectories (276 pairs)', ranges when the rows differ."""
    model = [r for r in rows if r.kind == "model" and r.info.get("replicates")]
    if not model:
        return ""
    reps = [r.info["replicates"] for r in model]
    trajs = [r.info["trajectories"] for r in model if r.info.get("trajectories")]
    pairs = [r.info["pairs"] for r in model if r.info.get("pairs")]
    text = f"n per cell = {_span(reps)} seed{'s' if max(reps) > 1 else ''}"
    if trajs and evaluation == "trajectory":  # camera tracking: frames, the first pose of each trajectory given
        text += (f" × {_span(trajs)} test trajectories ({_span(pairs)} frames after each trajectory's given first "
                 f"pose: what CTF scores; ATE also counts the {_span(trajs)} first frames)")
    elif trajs:
        text += f" × {_span(trajs)} test trajectories ({_span(pairs)} pairs)"
        if folds:
            text += f" of {len(folds)} held-out patient{'s' if len(folds) > 1 else ''}"
    elif folds:
        text += f" ({len(folds)} held-out patients)"
    del evaluation
    return text + "."


def budget_text(runs: Sequence[RunRecord]) -> str:
    """Optimiser steps, pairs seen, epochs and stop reasons of the runs behind a table."""
    if not runs:
        return ""

    def got(name: str) -> list[float]:
        return [float(r.metrics[name]) for r in runs if name in r.metrics]

    steps, seen, epochs = got("train.steps"), got("train.pairs_seen"), got("train.epochs")
    parts = []
    if steps:
        parts.append(f"{_span(steps)} optimiser steps")
    if seen:
        parts.append(f"{_span(seen)} pairs seen (batch × steps)")
    if epochs:
        parts.append(f"{_span(epochs, '{:.1f}')} epochs")
    reasons = Counter(stop_reasons(runs))
    stop = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items()))
    text = "Budget per run: " + (", ".join(parts) if parts else "not logged")
    return text + f"; stop reasons: {stop}."


def init_text(runs: Sequence[RunRecord]) -> str:
    """How the runs' backbones were initialised (their ``init`` tag): random, ImageNet or a file."""
    if not runs:
        return ""
    seen = Counter(r.tag(TAG_INIT) for r in runs)
    parts = []
    for init, n in sorted(seen.items()):
        if init == "random":
            what = "random weights (no pretrained backbone)"
        elif init.startswith("imagenet:"):
            what = f"ImageNet weights (torchvision {init.split(':', 1)[1]})"
        elif init.startswith("file:"):
            what = f"weights from the file {init.split(':', 1)[1]}"
        else:
            what = "not recorded (runs made before the init tag: random unless model.pretrained was set)"
        parts.append(what + (f" ({n} of {len(runs)} runs)" if len(seen) > 1 else ""))
    return "Backbone initialisation: " + "; ".join(parts) + "."


def provenance(ctx: ReportContext, c: Collector) -> str:
    idx = ctx.index
    seeds = sorted(c.seeds, key=seed_key)
    source = (f"the runs of this config's cells (cell_key), {'staged plan' if idx.plan and idx.plan.staged else 'grid'}"
              if idx.plan is not None else "every cell run of the sweep (latest per cell)")
    size = f", train_trajectories {c.size}" if c.size else ""
    return (f"Sweep '{idx.sweep}' (MLflow experiment '{idx.experiment}'): {source}; pose frame '{c.frame}'{size}; "
            f"seed{'s' if len(seeds) != 1 else ''} {', '.join(seeds) or '-'}. The MLflow run ids are listed with "
            f"the table.")


PRECISION_NAMES = {"32": "fp32", "bf16-mixed": "bf16 autocast", "16-mixed": "fp16 autocast"}


def precision_text(table: Table) -> tuple[str, str]:
    """The caption's numerics statement and, when the rows trained at different precisions, a one-line warning.
    From each run's ``speed.precision`` param; ("", "") when no run logged it (runs made before speed settings)."""
    rows = {}
    for r in table.rows:
        got = sorted({PRECISION_NAMES.get(p, p) for run in r.info.get("runs", ())
                      if (p := getattr(run, "params", {}).get("speed.precision"))})
        if r.kind == "model" and got:
            rows[r.name] = "/".join(got)
    if not rows:
        return "", ""
    kinds = sorted(set(rows.values()))
    if len(kinds) == 1:
        return f"Numerics: every row trained at {kinds[0]} (speed.precision).", ""
    named = "; ".join(f"{name}: {p}" for name, p in rows.items())
    return (f"Numerics differ between rows ({named}; speed.precision, the per-architecture speed settings): a "
            f"difference between these rows includes their numerics."), (
            f"{table.key}: rows trained at different precisions ({', '.join(kinds)}): the caption names each row's; "
            f"set train.precision in the config to compare at equal numerics")


def references_text() -> str:
    return ("Zero motion / Training mean: image-blind references (every relative pose zero / the training set's "
            "mean relative pose), scored on the same test trajectories and averaged over the table's runs; "
            "reference intervals are over the test units only (trajectories, or patients for a new patient; the "
            "references do not depend on the seed). † = the row has not beaten an image-blind model: the interval "
            "of its paired comparison with the better reference on the shared test units (skill = 1 − error / "
            "reference error; for CTF the difference) does not lie above 0 — the same verdict colours the skill "
            "figure; per cell, no multiplicity correction.")


IGNORES_TEXT = "‡ after a row's loss: its predictions vary less than 5% of the ground truth's (pred.std_ratio.pos " \
               "< 0.05): it ignores its input."


def finish(table: Table, c: Collector, expected_empty: Sequence[str] = ()) -> Table:
    """Attach the warnings: lacking cells (one line), rows without trajectory errors, empty columns."""
    table.warnings = list(c.warnings)
    if c.lacking:
        table.warnings.append(f"{table.key}: lacks {len(c.lacking)} cell(s) (rows show — or fewer seeds): "
                              + "; ".join(c.lacking))
    with_runs = Table(table.key, table.title, table.headers, table.columns, [r for r in table.rows if r.runs])
    empty = missing_cells(with_runs, expected_empty)
    if empty:
        table.warnings.append(f"{table.key}: empty cells shown as —: {'; '.join(empty)}")
    return table
