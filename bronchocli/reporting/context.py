"""What every table builder shares: the report context, the per-table run finder, caption pieces.

``ReportContext`` holds the run index, the loader of each run's
``trajectory_errors.csv`` (cached), the statistical settings and the profiler
of the ablation table. ``Collector`` finds the runs of each table row — the
config's cells of the table's stage (config mode) or every (fold, seed) the
sweep has (sweep mode) — keeps complete replicates only, and remembers which
cells the table lacks, for one warning line per table.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

from .. import registry, runkeys
from ..runs.records import TAG_INIT
from .aggregate import Frames
from .collect import FOLD, SEED, Identity, RunIndex, RunRecord, identity_label, seed_key
from .judge import Line, Settings
from .table_model import Table, missing_cells

BRONCHOTRACK = ("convlstm", "ce")  # the paper's BronchoTrack, when no sota stage selected one
OFFSETNET = ("offsetnet", "mse")  # OffsetNet's own loss (Sganga et al.): MSE on position and rotation
ABLATION_LOSS = "ce"  # every architecture with BronchoTrack's loss, so the rows differ in architecture only


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


def arch_names(paper_tables: bool = False) -> dict[str, str]:
    """Architecture -> its row label, in the tables' row order (registry.py, read at each call: a registered
    architecture has rows too). ``paper_tables``: only the row groups of the personalized/cross-subject tables."""
    return {s.name: s.label for s in registry.table_order() if s.paper_tables or not paper_tables}


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
    image_size: int | None = None  # the frames' size the config's runs trained at (cell runs do not log it)
    profile_plans: Callable[[], Mapping[str, set]] | None = None  # profile -> its (arch, loss, population) combos
    _profiles: dict[str, Mapping[str, Any] | None] = field(default_factory=dict)
    _plans: Mapping[str, set] | None = None
    _frames: dict[str, Any] = field(default_factory=dict)

    def profile(self, arch: str) -> Mapping[str, Any] | None:
        if self.profiler is None:
            return None
        if arch not in self._profiles:
            self._profiles[arch] = self.profiler(arch)
        return self._profiles[arch]

    def planned_by(self) -> Mapping[str, set]:
        """Profile -> the (arch, rot_loss, population) combinations it plans (scope.profile_plans; read once)."""
        if self._plans is None:
            self._plans = self.profile_plans() if self.profile_plans is not None else {}
        return self._plans

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


def metric_words(key: str) -> str:
    """A selection metric's key in words: "val_best.pos_l2" -> "validation position L2"; a key the registry does
    not know stays as it is."""
    validated = runkeys.val_best_name(key) or runkeys.val_name(key)
    name = validated or key.split(".", 1)[-1]
    if name not in registry.metric_names():
        return key
    label = registry.metric(name).label
    label = label[0].lower() + label[1:] if label[1:2].islower() else label
    return f"validation {label}" if validated else label


def bronchotrack(index: RunIndex) -> tuple[str, str, str]:
    """(arch, rot_loss, how chosen, in words) of BronchoTrack: the sota stage's top-1 selection ("selected on
    validation position L2"), else ConvLSTM + MSE+CE, the paper's ("")."""
    sel = index.selections.get("sota")
    if sel and sel.get("selected"):
        first = sel["selected"][0]
        arch, loss = first.get("arch", BRONCHOTRACK[0]), first.get("rot_loss", BRONCHOTRACK[1])
        by = metric_words(sel["by"]) if sel.get("by") else "a validation metric"
        return arch, loss, f"selected on {by}"
    return (*BRONCHOTRACK, "")


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

    def ran(self, arch: str, loss: str) -> bool:
        """Whether (arch, loss) itself is a config cell of the table (config mode) or has a run (sweep mode): no
        cross product of the architectures and losses seen."""
        if self.expected is not None:
            return self.has(arch, loss)
        return any(i[0] == arch and i[1] == loss and i[2] == self.population for i in self.index.runs)

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

    def line(self, arch: str, loss: str, grouped: bool = False, extra: Sequence = ()) -> Line:
        """The row of (arch, loss): its runs and its model's one name (registry.model_name, with the runs'
        backbone and initialisation), as the row label or, ``grouped``, under its architecture's group."""
        runs = self.runs(arch, loss)
        first = runs[0] if runs else None
        how = (first.params.get(registry.BACKBONE_PARAM), first.tag(TAG_INIT)) if first is not None else (None, None)
        model = registry.model_name(arch, loss, *how)
        if not grouped:
            return Line("", model, runs, list(extra), model)
        group = registry.arch(arch).label if arch in registry.arch_names() else arch
        return Line(group, registry.grouped_label(arch, loss, *how), runs, list(extra), model)


def source_text(ctx: ReportContext, c: Collector) -> str:
    """Where the table's numbers come from (the source line under the footnotes, not the caption)."""
    idx = ctx.index
    seeds = sorted(c.seeds, key=seed_key)
    source = (f"the runs of this config's cells ({'staged plan' if idx.plan and idx.plan.staged else 'grid'})"
              if idx.plan is not None else "every cell run of the sweep (latest per cell)")
    size = f", {c.size} training trajectories per patient and lobe" if c.size else ""
    return (f"Sweep '{idx.sweep}' (MLflow experiment '{idx.experiment}'): {source}; pose frame '{c.frame}'{size}; "
            f"seed{'s' if len(seeds) != 1 else ''} {', '.join(seeds) or '-'}.")


PRECISION_NAMES = {"32": "fp32", "bf16-mixed": "bf16 autocast", "16-mixed": "fp16 autocast"}


def precision_text(table: Table) -> tuple[str, str, str]:
    """(source statement, note, warning) on the numerics the rows trained at: one precision -> a source line;
    rows at different precisions -> a note naming each row's (it is part of any difference between them) and a
    warning. From each run's precision param; empty when no run logged it (runs made before speed settings)."""
    rows = {}
    for r in table.rows:
        got = sorted({PRECISION_NAMES.get(p, p) for run in r.info.get("runs", ())
                      if (p := getattr(run, "params", {}).get("speed.precision"))})
        if r.kind == "model" and got:
            rows[r.name] = "/".join(got)
    if not rows:
        return "", "", ""
    kinds = sorted(set(rows.values()))
    if len(kinds) == 1:
        return f"Numerics: every row trained at {kinds[0]}.", "", ""
    named = "; ".join(f"{name}: {p}" for name, p in rows.items())
    return "", (f"Numerics differ between rows ({named}): a difference between these rows includes their "
                f"numerics."), (
            f"{table.key}: rows trained at different precisions ({', '.join(kinds)}): the table's note names each "
            f"row's; set train.precision in the config to compare at equal numerics")


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
