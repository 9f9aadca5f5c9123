"""Run collection for reports: one batched MLflow query per sweep, deduplicated to one run per cell.

``collect_runs(client, experiment_id, sweep)`` fetches every ``run_kind=cell``
run of the sweep with one paginated ``search_runs`` (tags filter, all
statuses), then keeps, per cell identity (arch, rot_loss, population, fold,
seed, pose_frame), the latest FINISHED run. Superseded FINISHED runs are
remembered as duplicates (the report warns about them) and cells that only
have FAILED/KILLED/RUNNING runs are remembered so a missing-cell warning can
say why the cell is empty. Optuna trials (``run_kind=trial``) never match.
"""

from __future__ import annotations

import gc
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Iterable, Iterator, Mapping, Sequence

from .. import tracking
from ..cells import FIELDS
from ..errors import BronchoError

if TYPE_CHECKING:
    from mlflow.entities import Run

IDENTITY = FIELDS  # a run's cell coordinates, from its tags
Identity = tuple[str, ...]


@dataclass(frozen=True)
class RunRecord:
    """What a report needs from one MLflow run (tags, final metrics, where its artifacts are)."""

    run_id: str
    status: str
    start_time: int
    tags: Mapping[str, str]
    metrics: Mapping[str, float]
    artifact_uri: str = ""

    @classmethod
    def from_run(cls, run: "Run") -> "RunRecord":
        info = run.info
        return cls(info.run_id, info.status, int(info.start_time or 0), dict(run.data.tags),
                   dict(run.data.metrics), info.artifact_uri or "")

    def tag(self, name: str) -> str:
        return self.tags.get(name, "") or ""

    @property
    def identity(self) -> Identity:
        return tuple(self.tag(k) for k in IDENTITY)  # type: ignore[return-value]

    @property
    def label(self) -> str:
        arch, loss, pop, fold, seed, frame, size = self.identity
        return f"{arch}/{loss}/{pop}" + (f"/{fold}" if fold else "") + f"/s{seed}/{frame}" + (f"/t{size}" if size else "")


@dataclass
class RunIndex:
    """The runs of one sweep: one FINISHED run per cell identity, plus what was left out and why."""

    sweep: str
    experiment: str
    runs: dict[Identity, RunRecord] = field(default_factory=dict)
    duplicates: dict[Identity, list[RunRecord]] = field(default_factory=dict)  # superseded FINISHED runs
    unfinished: dict[Identity, list[RunRecord]] = field(default_factory=dict)  # cells without a FINISHED run
    pose_frame: str = ""
    archs: frozenset[str] = frozenset()  # architectures with any run in the sweep (any status): the table rows
    losses: frozenset[str] = frozenset()  # rotation losses likewise

    def select(self, population: str, arch: str, rot_loss: str) -> list[RunRecord]:
        """Every kept run of one (population, arch, rot_loss), sorted by fold then seed."""
        found = [r for (a, lo, p, *_), r in self.runs.items() if (a, lo, p) == (arch, rot_loss, population)]
        return sorted(found, key=lambda r: (r.tag("fold"), _seed_key(r.tag("seed"))))

    def replicas(self, population: str) -> list[tuple[str, str]]:
        """The (fold, seed) pairs any kept run of the population has: what every table cell should pool."""
        pairs = {(fold, seed) for (_, _, p, fold, seed, *_) in self.runs if p == population}
        return sorted(pairs, key=lambda fs: (fs[0], _seed_key(fs[1])))

    def not_finished(self, population: str, arch: str, rot_loss: str) -> list[RunRecord]:
        return [r for (a, lo, p, *_), rs in self.unfinished.items() if (a, lo, p) == (arch, rot_loss, population)
                for r in rs]


def _seed_key(seed: str) -> tuple[int, str]:
    return (int(seed), "") if seed.lstrip("-").isdigit() else (0, seed)


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
        runs = tracking.search_runs(client, experiment_ids, {tracking.TAG_SWEEP: sweep, tracking.TAG_KIND: "cell"})
        return [RunRecord.from_run(r) for r in runs]


def index_runs(records: Iterable[RunRecord], sweep: str, experiment: str, pose_frame: str | None = None) -> RunIndex:
    """Deduplicate to the latest FINISHED run per identity and restrict to one pose frame.

    Raises BronchoError when the FINISHED runs mix pose frames and none was chosen:
    the two parameterisations give different numbers and must not share a table.
    """
    records = list(records)
    finished = [r for r in records if r.status == "FINISHED"]
    frames = sorted({r.tag("pose_frame") for r in finished})
    if pose_frame is None and len(frames) > 1:
        raise BronchoError(f"sweep {sweep!r} has FINISHED runs in several pose frames ({', '.join(frames)}); "
                           f"choose one with --pose-frame")
    chosen = pose_frame if pose_frame is not None else (frames[0] if frames else None)  # None: keep every run
    index = RunIndex(sweep=sweep, experiment=experiment, pose_frame=chosen or "",
                     archs=frozenset(r.tag("arch") for r in records),
                     losses=frozenset(r.tag("rot_loss") for r in records))
    by_identity: dict[Identity, list[RunRecord]] = {}
    for r in records:
        if chosen is None or r.tag("pose_frame") == chosen:
            by_identity.setdefault(r.identity, []).append(r)
    for ident, group in by_identity.items():
        done = sorted((r for r in group if r.status == "FINISHED"), key=lambda r: (r.start_time, r.run_id),
                      reverse=True)
        if done:
            index.runs[ident] = done[0]
            if len(done) > 1:
                index.duplicates[ident] = done[1:]
        else:
            index.unfinished[ident] = group
    return index


def collect_runs(client, experiment_name: str, sweep: str, pose_frame: str | None = None) -> RunIndex:
    """The report's view of a sweep in experiment ``experiment_name`` (BronchoError if it does not exist)."""
    exp = client.get_experiment_by_name(experiment_name)
    if exp is None:
        raise BronchoError(f"MLflow experiment {experiment_name!r} not found in the tracking store; "
                           f"run `bronchopose sweep` (or train) first, or pass --config/--set tracking.experiment=...")
    records = fetch_runs(client, [exp.experiment_id], sweep)
    if not records:
        raise BronchoError(f"no runs of sweep {sweep!r} (tag sweep={sweep}, run_kind=cell) in experiment "
                           f"{experiment_name!r}; pass --sweep NAME (the config's `name` when it ran)")
    return index_runs(records, sweep, experiment_name, pose_frame)
