"""Planning a sweep: its stages, the cells of each, the walk through them, and the claims rows.

A config without ``stages`` is one stage: its grid. With ``stages`` (the
paper's protocol), each stage expands the top-level grid updated by its own
``grid``; a stage with ``select`` keeps the ``top`` combinations of its
``source`` stage by a validation metric (``selection.py``) and crosses them
with its other grid axes; ``add`` appends fixed combinations. A cell wanted by
several stages is one cell (one key, one run).

``StageWalk`` is the one walk through the stages that every launcher uses:
the driver's submissions (``launch.submit_missing``, whatever the launcher)
and every worker (``stagework.work_stages``).
It plans once (the patient list read once), reads the recorded selections once
per decision, and holds the selection rule: a selecting stage's cells are
known once its selection is recorded; it is settled (computed and recorded,
the first writer wins) as soon as every cell of its source stage is done
(FINISHED, or FAILED with no retry left, on any machine).

``prepare`` runs in the parent ``bronchopose sweep`` process before any worker
starts, so one-time work never races between workers: the MLflow store and
experiment, the dataset (generated if missing) and the claims rows.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..cells import Cell, Selection, select
from ..config import Config, Stage, run_signature
from ..config.grid import source_of, stage_cells, stages_of
from ..generation import ensure_dataset
from ..generation.sources import planned_patients
from ..runs.client import client_for, experiment_id
from .order import claim_order
from .record import forget_deleted, rebuild
from .selection import settle_selection
from .storage import FAILED, FINISHED, PENDING, RUNNING, CellRow, SweepStore


DAMAGED = "damaged"  # the state shown for a claims row this code cannot use (``damage.py``)


def plan_key(cfg: Config) -> str:
    """Identifies the plan: the run settings, the grid and the stages (a changed config never reuses a selection)."""
    blob = json.dumps({"run": run_signature(cfg), "grid": cfg.grid.model_dump(mode="json"),
                       "stages": [s.model_dump(mode="json") for s in cfg.stages]}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


@dataclass
class StagePlan:
    stage: Stage
    cells: list[Cell] | None  # None: waits for the selection of its source stage
    selection: dict[str, Any] | None = None


@dataclass
class Step:
    """A stage as the walk reaches it: its cells (filtered by ``only``), or, when ``waits`` > 0, the number of
    cells of its ``source`` stage that are not done yet (the walk ends there)."""

    stage: Stage
    cells: list[Cell]
    settled: dict[str, Any] | None = None  # the selection this walk settled just now (worth printing)
    source: Stage | None = None
    waits: int = 0


class StageWalk:
    """The plan's stages in order, for every launcher: planned once, recorded selections read once per decision.

    ``store`` may be None (no selection is known: ``config --grid``) or anything with ``SweepStore.selection``
    (the report reads selections from MLflow). Walking (``steps``, ``work_left``) needs the claims table.
    """

    def __init__(self, cfg: Config, store: SweepStore | None, only: Selection | None = None, *,
                 sweep: str | None = None):
        self.cfg, self.store, self.only = cfg, store, only
        self.sweep = sweep or cfg.name
        self.key = plan_key(cfg)
        self.stages = stages_of(cfg)
        self.patients = planned_patients(cfg)  # read once: cross-subject folds come from the dataset's patients
        self.selections: dict[str, dict[str, Any]] = {}  # recorded ones: never change (the first writer wins)
        self._all: dict[str, list[Cell]] = {}  # every cell of each stage known so far
        self._mine: dict[str, list[Cell]] = {}  # the same, filtered by ``only``
        for stage in self.stages:
            if stage.select is None:
                self._all[stage.name] = stage_cells(cfg, stage, self.patients)
            elif (recorded := self._recorded(stage)) is not None:
                self.selections[stage.name] = recorded
                self._all[stage.name] = stage_cells(cfg, stage, self.patients, recorded["selected"])
        if only:
            select([c for cells in self._all.values() for c in cells], only)  # a value no cell has: a typo
        for name in self._all:
            self._filter(name)

    # -- what is known ---------------------------------------------------------------------------------
    def _recorded(self, stage: Stage) -> dict[str, Any] | None:
        return self.store.selection(self.sweep, self.key, stage.name) if self.store is not None else None

    def _filter(self, name: str) -> None:
        cells = self._all[name]
        self._mine[name] = select(cells, self.only) if self.only and cells else list(cells)

    def _learn(self, stage: Stage, selection: dict[str, Any]) -> None:
        self.selections[stage.name] = selection
        self._all[stage.name] = stage_cells(self.cfg, stage, self.patients, selection["selected"])
        self._filter(stage.name)

    def refresh(self) -> None:
        """Read the selections not known yet (one query each): another process may have recorded them."""
        for stage in self.stages:
            if stage.name not in self._all and (recorded := self._recorded(stage)) is not None:
                self._learn(stage, recorded)

    def cells(self, stage: Stage, *, mine: bool = True) -> list[Cell] | None:
        """The stage's cells (``mine``: filtered by ``only``); None while its selection is not known."""
        return (self._mine if mine else self._all).get(stage.name)

    def plans(self) -> list[StagePlan]:
        """Every stage with the cells known so far, filtered by ``only``."""
        return [StagePlan(s, self.cells(s), self.selections.get(s.name)) for s in self.stages]

    def known_cells(self) -> list[Cell]:
        """Every cell known so far (all stages, deduplicated in stage order), filtered by ``only``."""
        seen: dict[str, Cell] = {}
        for stage in self.stages:
            for c in self.cells(stage) or []:
                seen.setdefault(c.key, c)
        return list(seen.values())

    @property
    def complete(self) -> bool:
        """Every stage's cells are known (every selection recorded)."""
        return all(s.name in self._all for s in self.stages)

    def rows(self) -> Plan:
        """The known cells (after ``refresh``) with their stored rows."""
        self.refresh()
        return read_plan(self.store, self.sweep, self.known_cells())

    # -- the selection rule ----------------------------------------------------------------------------
    def decide(self, stage: Stage) -> Step:
        """Whether ``stage``'s cells are known: a grid stage's always; a selecting stage's once its selection is
        recorded (read now, once), or settled here because every cell of its source stage is done."""
        if stage.name in self._all:
            return Step(stage, self._mine[stage.name])
        if (recorded := self._recorded(stage)) is not None:
            self._learn(stage, recorded)
            return Step(stage, self._mine[stage.name])
        source = source_of(self.cfg, stage)
        source_cells = self._all.get(source.name) or []
        source_plan = read_plan(self.store, self.sweep, source_cells)
        left = cells_left(source_plan, self.cfg.sweep.max_retries) + len(source_plan.damaged())  # never without one
        if left:
            return Step(stage, [], source=source, waits=left)
        selection = settle_selection(self.cfg, self.store, stage, source, source_cells, self.key, self.sweep)
        self._learn(stage, selection)
        return Step(stage, self._mine[stage.name], settled=selection)

    def steps(self) -> Iterator[Step]:
        """The stages in order, each decided when the caller asks for it (after it has run the ones before);
        ends with the first stage that waits."""
        for stage in self.stages:
            step = self.decide(stage)
            yield step
            if step.waits:
                return

    # -- a detached launcher: what submissions to size ----------------------------------------------------------------------
    def estimate(self, stage: Stage) -> int:
        """Cells of a stage whose selection is not known yet: ``top`` combinations of its source's cells."""
        sel = stage.select
        assert sel is not None  # only a selecting stage can be unknown
        combos: list[dict] = []
        for c in self._all.get(source_of(self.cfg, stage).name) or []:
            combo = {f: getattr(c, f) for f in sel.over}
            if combo not in combos:
                combos.append(combo)
        return max(1, len(stage_cells(self.cfg, stage, self.patients, combos[: sel.top])))

    def work_left(self) -> list[tuple[Stage, int]]:
        """Per stage, in order: cells still to run or wait for (rows added for every known cell), or the
        estimate of a stage whose selection is not known yet."""
        self.refresh()
        out = []
        for stage in self.stages:
            cells = self.cells(stage)
            if cells is None:
                out.append((stage, self.estimate(stage)))
            else:
                plan = ensure_rows(self.cfg, self.store, cells, sweep=self.sweep)
                out.append((stage, cells_left(plan, self.cfg.sweep.max_retries)))
        return out


def plan_stages(cfg: Config, store: SweepStore | None, only: Selection | None = None,
                sweep: str | None = None) -> list[StagePlan]:
    """Every stage with the cells known so far (recorded selections are read from ``store``), filtered."""
    return StageWalk(cfg, store, only, sweep=sweep).plans()


def plan_cells(cfg: Config, only: Selection | None = None, store: SweepStore | None = None) -> list[Cell]:
    """Every cell known so far (all stages, deduplicated in stage order), filtered by ``only``."""
    return StageWalk(cfg, store, only).known_cells()


# -- the claims rows ----------------------------------------------------------------------------------


@dataclass
class Plan:
    sweep: str
    cells: list[Cell]
    rows: dict[str, CellRow] = field(default_factory=dict)  # by cell key; missing = not stored yet (pending)

    def state(self, cell: Cell) -> str:
        """The cell's state: its row's, ``DAMAGED`` for a row set aside (``damage.py``), pending without a row."""
        row = self.rows.get(cell.key)
        return (DAMAGED if row.damage is not None else row.state) if row else PENDING

    def counts(self) -> dict[str, int]:
        out = {s: 0 for s in (FINISHED, RUNNING, FAILED, PENDING, DAMAGED)}
        for c in self.cells:
            out[self.state(c)] += 1
        return out

    def damaged(self) -> list[CellRow]:
        """The rows of the plan's cells set aside as damaged (``damage.py``), in the plan's order."""
        return [r for c in self.cells if (r := self.rows.get(c.key)) is not None and r.damage is not None]


def read_plan(store: SweepStore, sweep: str, cells: Sequence[Cell]) -> Plan:
    """The cells with their stored rows, without writing anything (``--dry-run``)."""
    rows = {r.cell_key: r for r in store.rows(sweep, [c.key for c in cells])} if store.exists() else {}
    return Plan(sweep, list(cells), rows)


def cells_left(plan: Plan, max_retries: int) -> int:
    """Cells still to run or to wait for (pending, running anywhere, or failed with a retry left); a damaged row is
    set aside, not waited for (``damage.py``)."""
    def done(c: Cell) -> bool:
        state = plan.state(c)
        return state in (FINISHED, DAMAGED) or (state == FAILED and not plan.rows[c.key].retryable(max_retries))

    return sum(1 for c in plan.cells if not done(c))


def claimable_now(plan: Plan, max_retries: int, now: float, stale_after_s: float) -> set[str]:
    """Keys of the cells a worker could claim at database time ``now``: pending, failed with a retry left, or
    running under a claim older than the staleness cut-off (its worker is dead). The storage's claim rule."""
    out = set()
    for c in plan.cells:
        row = plan.rows.get(c.key)
        if row is not None and row.damage is not None:
            continue
        if (row is None or row.state == PENDING or (row.state == FAILED and row.retryable(max_retries))
                or (row.state == RUNNING and (row.heartbeat is None or row.heartbeat < now - stale_after_s))):
            out.add(c.key)
    return out


def prepare_walk(cfg: Config, store: SweepStore, only: Selection | None = None, *, sweep: str | None = None,
                 dataset: bool = True, retry_failed: bool = False) -> tuple[StageWalk, Plan]:
    """Create the shared state once (MLflow store + experiment, dataset, claims tables), plan the stages and add
    the rows of every cell known so far; returns the walk and those rows with their state."""
    experiment_id(client_for(cfg), cfg)  # MLflow's first migration happens here, once
    if dataset:
        ensure_dataset(cfg)  # before planning: cross-subject folds come from the dataset's patients
    store.ensure_schema()
    walk = StageWalk(cfg, store, only, sweep=sweep)
    return walk, add_cells(cfg, store, walk.known_cells(), sweep=sweep, retry_failed=retry_failed)


def prepare(cfg: Config, store: SweepStore, only: Selection | None = None, *, sweep: str | None = None,
            dataset: bool = True, retry_failed: bool = False) -> Plan:
    """``prepare_walk`` for callers that need only the rows."""
    return prepare_walk(cfg, store, only, sweep=sweep, dataset=dataset, retry_failed=retry_failed)[1]


def add_cells(cfg: Config, store: SweepStore, cells: Sequence[Cell], *, sweep: str | None = None,
              retry_failed: bool = False) -> Plan:
    """Insert the cells' rows (idempotent) in claim order (``order.claim_order``: the longest first), record
    those FINISHED in MLflow, and return them with their state."""
    sweep = sweep or cfg.name
    store.add_cells(sweep, claim_order(cfg, cells))
    if retry_failed:
        store.reset_failed(sweep, [c.key for c in cells])
    forget_deleted(cfg, store, sweep, cells)  # a run deleted by hand in MLflow: its cell is not done (record.py)
    rebuild(cfg, store, sweep, cells)  # cells FINISHED in MLflow are done, whatever the table knew (record.py)
    return read_plan(store, sweep, cells)


def ensure_rows(cfg: Config, store: SweepStore, cells: Sequence[Cell], *, sweep: str | None = None) -> Plan:
    """The cells' rows, added (``add_cells``) only when some are missing: a stage settled just now, or one whose
    selection a process recorded before it could add them; cells prepared already are not asked MLflow again."""
    plan = read_plan(store, sweep or cfg.name, cells)
    return plan if len(plan.rows) == len(plan.cells) else add_cells(cfg, store, cells, sweep=sweep)


def open_store(cfg: Config, url: str | None = None) -> SweepStore:
    """The claims table of ``cfg`` (``url``: the real URL where ``cfg``'s is redacted, as in a worker's config)."""
    return SweepStore(url or cfg.paths.storage_url, cfg.runs.timeout_s, cfg.runs.busy_timeout_s)

