"""Planning a sweep: its stages, the cells of each, the selections between them, and the shared state.

A config without ``stages`` is one stage: its grid. With ``stages`` (the
paper's protocol), each stage expands the top-level grid updated by its own
``grid``; a stage with ``select`` keeps the ``top`` combinations (values of
the ``over`` fields, e.g. arch and rot_loss) of its ``source`` stage, ranked by
the mean over that stage's FINISHED runs of a validation metric (never a test
metric), and crosses them with its other grid axes; ``add`` appends fixed
combinations. A cell wanted by several stages is one cell (one key, one run).

The selection is computed once the source stage's cells are all done, by
whichever sweep process gets there first, and recorded in the storage
(``record_selection`` keeps the first); every process then uses the recorded
one, so machines agree. The recording process also logs it to MLflow as a
``run_kind=selection`` run (``selection.json``: the ranking with every value).

``prepare`` runs in the parent ``bronchopose sweep`` process before any worker
starts, so one-time work never races between workers: the MLflow store and
experiment, the dataset (generated if missing) and the claims rows.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..cells import Cell, Selection, select
from ..config import Config, Stage, expand_grid, run_signature
from ..errors import BronchoError
from ..generation import ensure_dataset
from ..generation.sources import planned_patients
from ..runs.client import client_for, experiment_id
from ..runs.parents import sweep_parent
from ..runs.records import TAG_CELL_KEY, TAG_KIND, TAG_PARENT, TAG_SWEEP, log_params, search_runs
from .storage import FAILED, FINISHED, PENDING, RUNNING, CellRow, SweepStore

TAG_STAGE = "stage"
TAG_PLAN = "plan_key"


def stages_of(cfg: Config) -> list[Stage]:
    return list(cfg.stages) or [Stage(name="grid")]


def plan_key(cfg: Config) -> str:
    """Identifies the plan: the run settings, the grid and the stages (a changed config never reuses a selection)."""
    blob = json.dumps({"run": run_signature(cfg), "grid": cfg.grid.model_dump(mode="json"),
                       "stages": [s.model_dump(mode="json") for s in cfg.stages]}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def source_of(cfg: Config, stage: Stage) -> Stage:
    stages = stages_of(cfg)
    if stage.source is not None:
        return next(s for s in stages if s.name == stage.source)
    return stages[[s.name for s in stages].index(stage.name) - 1]


def stage_cells(cfg: Config, stage: Stage, patients: Sequence[str] | None,
                combos: Sequence[dict[str, Any]] = ()) -> list[Cell]:
    """The cells of ``stage``: its grid, restricted to ``combos`` when it selects, plus its ``add`` entries."""
    grid = stage.stage_grid(cfg.grid)
    wanted = list(combos) if stage.select is not None else [{}]
    wanted += list(stage.add)
    out: dict[str, Cell] = {}
    for combo in wanted:
        g = grid.model_copy(update={k: [v] for k, v in combo.items()})
        for cell in expand_grid(cfg, patients, g):
            out.setdefault(cell.key, cell)
    return list(out.values())


@dataclass
class StagePlan:
    stage: Stage
    cells: list[Cell] | None  # None: waits for the selection of its source stage
    selection: dict[str, Any] | None = None


def plan_stages(cfg: Config, store: SweepStore | None, only: Selection | None = None,
                sweep: str | None = None) -> list[StagePlan]:
    """Every stage with the cells known so far (recorded selections are read from ``store``), filtered."""
    patients = planned_patients(cfg)
    key = plan_key(cfg)
    out = []
    for stage in stages_of(cfg):
        if stage.select is None:
            out.append(StagePlan(stage, stage_cells(cfg, stage, patients)))
            continue
        recorded = store.selection(sweep or cfg.name, key, stage.name) if store is not None else None
        cells = None if recorded is None else stage_cells(cfg, stage, patients, recorded["selected"])
        out.append(StagePlan(stage, cells, recorded))
    if only:
        known = [c for sp in out for c in sp.cells or []]
        select(known, only)  # a value no known cell has is an error (a typo)
        for sp in out:
            if sp.cells is not None:
                sp.cells = select(sp.cells, only) if sp.cells else []
    return out


def plan_cells(cfg: Config, only: Selection | None = None, store: SweepStore | None = None) -> list[Cell]:
    """Every cell known so far (all stages, deduplicated in stage order), filtered by ``only``."""
    seen: dict[str, Cell] = {}
    for sp in plan_stages(cfg, store, only):
        for c in sp.cells or []:
            seen.setdefault(c.key, c)
    return list(seen.values())


# -- selection ----------------------------------------------------------------------------------------


def _finished_runs(cfg: Config, cells: Sequence[Cell]) -> dict[str, Any]:
    """The latest FINISHED MLflow run of each cell key (missing keys: no FINISHED run)."""
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    keys = {c.key for c in cells}
    runs = search_runs(client, [exp], {TAG_SWEEP: cfg.name, TAG_KIND: "cell"},
                                ["FINISHED"])
    out: dict[str, Any] = {}
    for r in runs:  # newest first
        k = r.data.tags.get(TAG_CELL_KEY)
        if k in keys and k not in out:
            out[k] = r
    return out


def compute_selection(cfg: Config, stage: Stage, source_cells: Sequence[Cell]) -> dict[str, Any]:
    """Rank the source stage's combinations by the mean of ``select.by`` over their FINISHED runs; keep ``top``."""
    sel = stage.select
    assert sel is not None
    runs = _finished_runs(cfg, source_cells)
    groups: dict[tuple, list[tuple[Cell, Any]]] = {}
    for c in source_cells:
        groups.setdefault(tuple(getattr(c, f) for f in sel.over), []).append((c, runs.get(c.key)))
    ranked = []
    for combo, members in groups.items():
        values = [r.data.metrics[sel.by] for _, r in members if r is not None and sel.by in r.data.metrics]
        ranked.append({
            "combo": dict(zip(sel.over, combo)),
            "value": sum(values) / len(values) if values else None,
            "runs": len(values), "cells": len(members),
            "run_ids": [r.info.run_id for _, r in members if r is not None],
        })
    ranked.sort(key=lambda e: (e["value"] is None, e["value"] if e["value"] is not None else 0.0,
                               json.dumps(e["combo"], sort_keys=True)))
    chosen = [e["combo"] for e in ranked if e["value"] is not None][: sel.top]
    if not chosen:
        raise BronchoError(f"stage {stage.name}: no FINISHED run of stage {source_of(cfg, stage).name} has metric "
                           f"{sel.by!r} to select by")
    return {"stage": stage.name, "source": source_of(cfg, stage).name, "by": sel.by, "top": sel.top,
            "over": list(sel.over), "ranked": ranked, "selected": chosen}


def _log_selection(cfg: Config, selection: dict[str, Any], key: str) -> None:
    """The selection as an MLflow run (``run_kind=selection``), so it can be reviewed beside the cells."""
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    run = client.create_run(exp, tags={
        TAG_SWEEP: cfg.name, TAG_KIND: "selection", TAG_STAGE: selection["stage"], TAG_PLAN: key,
        "mlflow.runName": f"selection-{selection['stage']}", TAG_PARENT: sweep_parent(client, cfg, exp),
    })
    run_id = run.info.run_id
    log_params(client, run_id, {"by": selection["by"], "top": str(selection["top"]),
                                          "source": selection["source"], "over": ",".join(selection["over"]),
                                          "selected": json.dumps(selection["selected"])})
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "selection.json"
        path.write_text(json.dumps(selection, indent=2))
        client.log_artifact(run_id, str(path))
    client.set_terminated(run_id, "FINISHED")


def settle_selection(cfg: Config, store: SweepStore, stage: Stage, source_cells: Sequence[Cell],
                     sweep: str | None = None) -> dict[str, Any]:
    """The stage's selection: the recorded one, or computed now and recorded (the first writer wins)."""
    sweep = sweep or cfg.name
    key = plan_key(cfg)
    recorded = store.selection(sweep, key, stage.name)
    if recorded is not None:
        return recorded
    selection = compute_selection(cfg, stage, source_cells)
    if store.record_selection(sweep, key, stage.name, selection):
        _log_selection(cfg, selection, key)
        return selection
    return store.selection(sweep, key, stage.name) or selection


def describe_selection(selection: dict[str, Any]) -> str:
    """One line: which combinations went on, by which metric, with which values."""
    chosen = [json.dumps(c, sort_keys=True) for c in selection["selected"]]
    values = {json.dumps(e["combo"], sort_keys=True): e for e in selection["ranked"]}
    parts = [f"{'/'.join(str(v) for v in json.loads(c).values())} {values[c]['value']:.4g} "
             f"({values[c]['runs']} run{'s' if values[c]['runs'] != 1 else ''})" for c in chosen]
    return (f"stage {selection['stage']}: top {selection['top']} of stage {selection['source']} by "
            f"{selection['by']} (validation, mean over runs): " + ", ".join(parts))


# -- the claims rows ----------------------------------------------------------------------------------


@dataclass
class Plan:
    sweep: str
    cells: list[Cell]
    rows: dict[str, CellRow] = field(default_factory=dict)  # by cell key; missing = not stored yet (pending)

    def state(self, cell: Cell) -> str:
        row = self.rows.get(cell.key)
        return row.state if row else PENDING

    def counts(self) -> dict[str, int]:
        out = {s: 0 for s in (FINISHED, RUNNING, FAILED, PENDING)}
        for c in self.cells:
            out[self.state(c)] += 1
        return out


def read_plan(store: SweepStore, sweep: str, cells: Sequence[Cell]) -> Plan:
    """The cells with their stored rows, without writing anything (``--dry-run``)."""
    rows = {r.cell_key: r for r in store.rows(sweep, [c.key for c in cells])} if store.exists() else {}
    return Plan(sweep, list(cells), rows)


def prepare(cfg: Config, store: SweepStore, only: Selection | None = None, *, sweep: str | None = None,
            dataset: bool = True, retry_failed: bool = False) -> Plan:
    """Create the shared state once (MLflow store + experiment, dataset, claims tables) and the rows of every
    cell known so far; returns them with their state."""
    experiment_id(client_for(cfg), cfg)  # MLflow's first migration happens here, once
    if dataset:
        ensure_dataset(cfg)  # before expanding: cross-subject folds come from the dataset's patients
    store.ensure_schema()
    return add_cells(cfg, store, plan_cells(cfg, only, store), sweep=sweep, retry_failed=retry_failed)


def add_cells(cfg: Config, store: SweepStore, cells: Sequence[Cell], *, sweep: str | None = None,
              retry_failed: bool = False) -> Plan:
    """Insert the cells' rows (idempotent) and return them with their state."""
    sweep = sweep or cfg.name
    store.add_cells(sweep, cells)
    if retry_failed:
        store.reset_failed(sweep, [c.key for c in cells])
    return read_plan(store, sweep, cells)
