"""Run collection for reports: one batched MLflow query per sweep, one run per cell.

``fetch_runs`` gets every ``run_kind=cell`` run of a sweep with one paginated
``search_runs`` (all statuses; Optuna trials never match). ``index_runs`` then
keeps one FINISHED run per cell identity (arch, rot_loss, population, fold,
seed, pose_frame, train_trajectories):

* **config mode** (a ``PlanView`` is given): only runs whose ``cell_key`` is
  the key of one of the config's cells; the latest FINISHED run per key.
  Runs of the sweep with other keys (made under another config) are counted
  and left out, unless ``include_other_configs``;
* **sweep mode** (no plan, or ``include_other_configs``): every cell run of
  the sweep, the latest FINISHED per identity, with a note when one identity
  has runs with different keys (the sweep mixes configs).

Superseded FINISHED runs are remembered as duplicates and cells with only
FAILED/KILLED/RUNNING runs as unfinished, so warnings can say why a cell is
empty. The index keeps every pose frame and training-set size; the main
tables use ``index.pose_frame`` and ``index.train_size``.
"""

from __future__ import annotations

import gc
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Iterator, Mapping, Sequence
from urllib.parse import urlparse
from urllib.request import url2pathname

from .. import registry
from ..cells import FIELDS
from ..errors import BronchoError
from ..runs.client import find_experiment
from ..runs.records import (TAG_CELL_KEY, TAG_INIT, TAG_KIND, TAG_SWEEP, deleted_cell_runs, deleted_runs_line, run_title_of,
                            search_runs)
from ..runs.views import config_value
from .scope import PlanView, fetch_selections

if TYPE_CHECKING:
    from mlflow.entities import Run

IDENTITY = FIELDS  # a run's cell coordinates, from its tags
Identity = tuple[str, ...]
ARCH, LOSS, POP, FOLD, SEED, FRAME, SIZE = range(len(FIELDS))


@dataclass(frozen=True)
class RunRecord:
    """What a report needs from one MLflow run (tags, final metrics, where its artifacts are)."""

    run_id: str
    status: str
    start_time: int
    tags: Mapping[str, str]
    metrics: Mapping[str, float]
    artifact_uri: str = ""
    params: Mapping[str, str] = field(default_factory=dict)  # e.g. speed.precision (the captions' numerics)

    @classmethod
    def from_run(cls, run: "Run") -> "RunRecord":
        info = run.info
        return cls(info.run_id, info.status, int(info.start_time or 0), dict(run.data.tags),
                   dict(run.data.metrics), info.artifact_uri or "", dict(run.data.params))

    def tag(self, name: str) -> str:
        return self.tags.get(name, "") or ""

    def setting(self, name: str) -> float | None:
        """A numeric config constant the run logged (``eval.ctf_angle``, ...): its param, or its metric on runs
        logged before it was a param; None when it has neither."""
        return config_value(self.params, self.metrics, name)

    @property
    def artifacts_gone(self) -> Path | None:
        """The run's local artifact folder when it no longer exists (deleted or moved); None otherwise or remote."""
        uri = self.artifact_uri
        if uri.startswith("file:"):
            folder = Path(url2pathname(urlparse(uri).path))
        elif uri and "://" not in uri:
            folder = Path(uri)
        else:
            return None
        return None if folder.exists() else folder

    @property
    def key(self) -> str:
        return self.tag(TAG_CELL_KEY)

    @property
    def identity(self) -> Identity:
        return tuple(self.tag(k) for k in IDENTITY)  # type: ignore[return-value]

    @property
    def label(self) -> str:
        return identity_label(self.identity)

    @property
    def title(self) -> str:
        """The run's name in figure legends: the UI's run name (records.run_title: the model's name, its seed and
        the coordinates)."""
        return run_title_of(self.tags, self.params)

    @property
    def model(self) -> str:
        """The run's model by its one name (registry.model_name: architecture, loss, backbone, initialisation)."""
        return registry.model_name(self.tag("arch"), self.tag("rot_loss"), self.params.get(registry.BACKBONE_PARAM),
                                   self.tag(TAG_INIT))


def identity_label(ident: Identity) -> str:
    arch, loss, pop, fold, seed, frame, size = ident
    return f"{arch}/{loss}/{pop}" + (f"/{fold}" if fold else "") + f"/s{seed}/{frame}" + (f"/t{size}" if size else "")


def seed_key(seed: str) -> tuple[int, str]:
    return (int(seed), "") if seed.lstrip("-").isdigit() else (0, seed)


def size_key(size: str) -> tuple[int, int]:
    """Sort key of a train_trajectories tag: numbers ascending, the default ("") last (it is the full split)."""
    return (1, 0) if size == "" else (0, int(size))


@dataclass
class RunIndex:
    """The runs a report uses: one FINISHED run per cell identity, plus what was left out and why."""

    sweep: str
    experiment: str
    runs: dict[Identity, RunRecord] = field(default_factory=dict)
    duplicates: dict[Identity, list[RunRecord]] = field(default_factory=dict)  # superseded FINISHED runs
    unfinished: dict[Identity, list[RunRecord]] = field(default_factory=dict)  # cells without a FINISHED run
    pose_frame: str = ""  # the pose frame of the main tables
    train_size: str = ""  # the train_trajectories tag of the main tables ("" = the split's default)
    archs: frozenset[str] = frozenset()  # architectures with any run in the sweep (any status): sweep-mode rows
    losses: frozenset[str] = frozenset()
    plan: PlanView | None = None  # config mode: the config's cells
    selections: dict[str, dict] = field(default_factory=dict)  # stage -> recorded selection (sweep mode too)
    other_configs: int = 0  # runs of the sweep with cell keys of another config, left out
    notes: list[str] = field(default_factory=list)  # index-level warnings (one line each)

    def select(self, population: str, arch: str, rot_loss: str, frame: str | None = None,
               size: str | None = None) -> list[RunRecord]:
        """Kept runs of one (population, arch, rot_loss) in a frame and size (default: the main tables'),
        sorted by fold then seed."""
        frame = self.pose_frame if frame is None else frame
        size = self.train_size if size is None else size
        want = (arch, rot_loss, population)
        found = [r for ident, r in self.runs.items()
                 if (ident[ARCH], ident[LOSS], ident[POP]) == want and ident[FRAME] == frame and ident[SIZE] == size]
        return sorted(found, key=lambda r: (r.tag("fold"), seed_key(r.tag("seed"))))

    def expected(self, table: str, population: str, frame: str | None = None,
                 size: str | None = None) -> list[Identity] | None:
        """Config mode: the cells of the table's stage in one population, frame and size. None in sweep mode."""
        if self.plan is None:
            return None
        frame = self.pose_frame if frame is None else frame
        size = self.train_size if size is None else size
        return [i for i in self.plan.cells(table) if i[POP] == population and i[FRAME] == frame and i[SIZE] == size]

    def replicas(self, population: str, frame: str | None = None, size: str | None = None) -> list[tuple[str, str]]:
        """Sweep mode: the (fold, seed) pairs any run of the population has (any status): what a row should have."""
        frame = self.pose_frame if frame is None else frame
        size = self.train_size if size is None else size
        every = list(self.runs) + list(self.unfinished)
        pairs = {(i[FOLD], i[SEED]) for i in every if i[POP] == population and i[FRAME] == frame and i[SIZE] == size}
        return sorted(pairs, key=lambda fs: (fs[0], seed_key(fs[1])))

    def not_finished(self, ident: Identity) -> list[RunRecord]:
        return self.unfinished.get(ident, [])

    def values(self, position: int, population: str | None = None) -> list[str]:
        """The distinct values of one identity field among the kept runs (optionally of one population)."""
        return sorted({i[position] for i in self.runs if population is None or i[POP] == population})

    def frames(self) -> list[str]:
        return self.values(FRAME)

    def sizes(self, population: str | None = None, frame: str | None = None) -> list[str]:
        frame = self.pose_frame if frame is None else frame
        found = {i[SIZE] for i in self.runs if (population is None or i[POP] == population) and i[FRAME] == frame}
        return sorted(found, key=size_key)


@contextmanager
def _gc_paused() -> Iterator[None]:
    """Pause the cyclic garbage collector: MLflow's SQL store builds ~150 ORM objects per run (params,
    metrics, tags), and the collector rescanning them while they pile up makes a 500-run query ~4x slower."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def fetch_runs(client, experiment_ids: Sequence[str], sweep: str) -> list[RunRecord]:
    """Every cell run of ``sweep`` (all statuses, newest first): one paginated MLflow query."""
    with _gc_paused():
        runs = search_runs(client, experiment_ids, {TAG_SWEEP: sweep, TAG_KIND: "cell"})
        return [RunRecord.from_run(r) for r in runs]


def _latest_first(runs: Iterable[RunRecord]) -> list[RunRecord]:
    return sorted(runs, key=lambda r: (r.start_time, r.run_id), reverse=True)


def _keep(index: RunIndex, groups: Mapping[Identity, list[RunRecord]]) -> None:
    """The latest FINISHED run of each group; the rest are duplicates, or the group is unfinished."""
    for ident, group in groups.items():
        done = _latest_first(r for r in group if r.status == "FINISHED")
        if done:
            index.runs[ident] = done[0]
            if len(done) > 1:
                index.duplicates[ident] = done[1:]
        elif group:
            index.unfinished[ident] = group


def _by_config(index: RunIndex, records: list[RunRecord], plan: PlanView) -> None:
    by_key: dict[str, list[RunRecord]] = {}
    for r in records:
        by_key.setdefault(r.key, []).append(r)
    _keep(index, {ident: by_key.get(key, []) for ident, key in plan.keys.items()})
    wanted = set(plan.keys.values())
    others = [r for r in records if r.key not in wanted]
    index.other_configs = len(others)
    if others:
        finished = sum(r.status == "FINISHED" for r in others)
        index.notes.append(f"config: left out {len(others)} run(s) of sweep {index.sweep!r} ({finished} FINISHED) "
                           f"whose cell_key is not a cell of this config (made under another config); "
                           f"--include-other-configs uses them")


def _by_identity(index: RunIndex, records: list[RunRecord]) -> None:
    groups: dict[Identity, list[RunRecord]] = {}
    for r in records:
        groups.setdefault(r.identity, []).append(r)
    _keep(index, groups)
    mixed = [ident for ident, group in groups.items()
             if len({r.key for r in group if r.status == "FINISHED"}) > 1]
    if mixed:
        index.notes.append(f"config: sweep {index.sweep!r} mixes configs: {len(mixed)} cell(s) have FINISHED runs "
                           f"with different cell keys (e.g. {identity_label(mixed[0])}); each uses its latest run")


def _choose(values: Sequence[str], preferred: str, sort_key, what: str, option: str, notes: list[str]) -> str:
    if len(values) <= 1:
        return values[0] if values else preferred
    chosen = preferred if preferred in values else sorted(values, key=sort_key)[-1]
    notes.append(f"{what}: the runs span {', '.join(v or 'default' for v in values)}; the main tables use "
                 f"{chosen or 'default'}{option}")
    return chosen


def index_runs(records: Iterable[RunRecord], sweep: str, experiment: str, pose_frame: str | None = None, *,
               plan: PlanView | None = None, include_other_configs: bool = False) -> RunIndex:
    """Deduplicate ``records`` to one FINISHED run per cell (see the module doc) and pick the main tables'
    pose frame (``pose_frame`` or the only one; ``world`` when the runs span both) and training-set size
    (the default split when present, else the largest)."""
    records = list(records)
    index = RunIndex(sweep=sweep, experiment=experiment, plan=plan,
                     archs=frozenset(r.tag("arch") for r in records),
                     losses=frozenset(r.tag("rot_loss") for r in records))
    if plan is not None and not include_other_configs:
        _by_config(index, records, plan)
    else:
        _by_identity(index, records)
    if plan is not None:
        index.archs = frozenset(i[ARCH] for i in plan.keys)
        index.losses = frozenset(i[LOSS] for i in plan.keys)
        index.selections = dict(plan.selections)
        for stage in plan.pending():
            index.notes.append(f"plan: stage {stage!r} has no recorded selection yet (its cells are not known; "
                               f"run `bronchopose sweep` to finish the earlier stage)")
    known = set(index.runs) | set(plan.keys if plan is not None else ())
    frames = sorted({i[FRAME] for i in known})
    if pose_frame is not None:
        index.pose_frame = pose_frame
    else:
        index.pose_frame = _choose(frames, "world", str, "pose frame", " (--pose-frame chooses; the frames table "
                                   "compares both)", index.notes)
    sizes = sorted({i[SIZE] for i in known if i[FRAME] == index.pose_frame}, key=size_key)
    index.train_size = _choose(sizes, "", size_key, "train_trajectories", " (fig-learning-curve shows every size)",
                               index.notes)
    return index


def stop_reasons(runs: Iterable[RunRecord]) -> Counter:
    return Counter(r.tag("stop_reason") or "unknown" for r in runs)


def collect_runs(client, experiment_name: str, sweep: str, pose_frame: str | None = None, *,
                 plan: PlanView | None = None, include_other_configs: bool = False,
                 selections: bool = True) -> RunIndex:
    """The report's view of a sweep in experiment ``experiment_name`` (BronchoError if it does not exist).

    Without ``plan`` the recorded selections of the sweep (latest per stage, any plan) are read too, so the
    sota table can name the selected model.
    """
    exp = find_experiment(client, experiment_name)  # deleted by hand: the one line every command gives
    if exp is None:
        raise BronchoError(f"MLflow experiment {experiment_name!r} not found in the MLflow store; "
                           f"run `bronchopose sweep` (or train) first, or pass --config/--set runs.experiment=...")
    records = fetch_runs(client, [exp.experiment_id], sweep)
    gone = deleted_cell_runs(client, exp.experiment_id, sweep)  # runs deleted by hand: said, not guessed at
    gone = {k: r for k, r in gone.items() if not any(rec.tag(TAG_CELL_KEY) == k and rec.status == "FINISHED"
                                                   for rec in records)}
    if not records:
        if gone:
            raise BronchoError(deleted_runs_line(len(gone), sweep, experiment_name))
        raise BronchoError(f"no runs of sweep {sweep!r} (tag sweep={sweep}, run_kind=cell) in experiment "
                           f"{experiment_name!r}; pass --sweep NAME (the config's `name` when it ran)")
    index = index_runs(records, sweep, experiment_name, pose_frame, plan=plan,
                       include_other_configs=include_other_configs)
    if gone:
        index.notes.append(deleted_runs_line(len(gone), sweep, experiment_name))
    if plan is None and selections:
        index.selections = fetch_selections(client, [exp.experiment_id], sweep, None)
    return index
