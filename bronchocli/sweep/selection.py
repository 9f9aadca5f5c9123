"""A selecting stage's choice: rank its source stage's combinations by a validation metric, record the top ones.

A stage with ``select`` keeps the ``top`` combinations (values of the ``over``
fields, e.g. arch and rot_loss) of its ``source`` stage, ranked by the mean
over that stage's FINISHED runs of a validation metric (never a test metric).
The selection is computed once the source stage's cells are all done, by
whichever sweep process gets there first, and recorded in the storage
(``record_selection`` keeps the first); every process then uses the recorded
one, so machines agree. The recording process also logs it to MLflow as a
``run_kind=selection`` run (``selection.json``: the ranking with every value).

When a stage is decided (and with which cells) is the stage walker's job
(``plan.StageWalk``); this module only ranks, records and describes.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..cells import Cell
from ..config import Config, Stage
from ..errors import BronchoError
from ..runs.client import client_for, experiment_id
from ..runs.parents import sweep_parent
from ..runs.records import TAG_CELL_KEY, TAG_KIND, TAG_PARENT, TAG_SWEEP, log_params, search_runs
from .storage import SweepStore

TAG_STAGE = "stage"
TAG_PLAN = "plan_key"


def finished_runs(cfg: Config, cells: Sequence[Cell], sweep: str | None = None) -> dict[str, Any]:
    """The latest FINISHED MLflow run of each cell key of sweep ``sweep`` (default: the config's; missing keys:
    no FINISHED run)."""
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    keys = {c.key for c in cells}
    runs = search_runs(client, [exp], {TAG_SWEEP: sweep or cfg.name, TAG_KIND: "cell"}, ["FINISHED"])
    out: dict[str, Any] = {}
    for r in runs:  # newest first
        k = r.data.tags.get(TAG_CELL_KEY)
        if k in keys and k not in out:
            out[k] = r
    return out


def compute_selection(cfg: Config, stage: Stage, source: Stage, source_cells: Sequence[Cell]) -> dict[str, Any]:
    """Rank the source stage's combinations by the mean of ``select.by`` over their FINISHED runs; keep ``top``."""
    sel = stage.select
    assert sel is not None
    runs = finished_runs(cfg, source_cells)
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
        raise BronchoError(f"stage {stage.name}: no FINISHED run of stage {source.name} has metric "
                           f"{sel.by!r} to select by")
    return {"stage": stage.name, "source": source.name, "by": sel.by, "top": sel.top,
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


def settle_selection(cfg: Config, store: SweepStore, stage: Stage, source: Stage, source_cells: Sequence[Cell],
                     key: str, sweep: str) -> dict[str, Any]:
    """The stage's selection (plan ``key``): the recorded one, or computed now and recorded (the first writer
    wins)."""
    recorded = store.selection(sweep, key, stage.name)
    if recorded is not None:
        return recorded
    selection = compute_selection(cfg, stage, source, source_cells)
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
