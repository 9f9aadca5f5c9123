"""Which cells a report covers: the config's plan (stages, recorded selections) as cell identities.

A report made from a config uses only the runs of the config's cells (their
``cell_key``), so runs a sweep made under an earlier config never leak into a
table. The cells come from ``sweep.plan.plan_stages`` exactly as the sweep
planned them; a stage that selects from an earlier one uses the selection the
sweep recorded, read back from its MLflow ``run_kind=selection`` run (tag
``plan_key`` = this config's plan key), so a report needs only MLflow and the
config, not the sweep's claims store.

Tables map to stages by name when the config has stages (``personalized``,
``cross-subject``, ``sota``); a table whose stage the config lacks, and every
table of a config without stages, uses all the plan's cells.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from ..cells import FIELDS, Cell
from ..config import Config, load_config
from ..errors import BronchoError
from ..runs.records import TAG_KIND, TAG_SWEEP, search_runs
from ..sweep.plan import plan_key, plan_stages
from ..sweep.selection import TAG_PLAN, TAG_STAGE

Identity = tuple[str, ...]
TABLE_STAGES = {"personalized": "personalized", "cross-subject": "cross-subject", "sota": "sota"}


def identity_of(cell: Cell) -> Identity:
    tags = cell.tags()
    return tuple(tags[k] for k in FIELDS)


@dataclass
class PlanView:
    """The config's cells by stage (``None``: a selecting stage whose selection is not recorded yet)."""

    stages: dict[str, list[Identity] | None]
    keys: dict[Identity, str]  # every known cell -> its key
    staged: bool = False
    selections: dict[str, dict[str, Any]] = field(default_factory=dict)

    def cells(self, table: str) -> list[Identity]:
        """The cells a table draws from: its stage's when the config has that stage, else every known cell."""
        stage = TABLE_STAGES.get(table)
        if self.staged and stage in self.stages:
            return list(self.stages[stage] or [])
        return list(self.keys)

    def pending(self) -> list[str]:
        return [name for name, cells in self.stages.items() if cells is None]


class _RecordedSelections:
    """The ``store`` ``plan_stages`` asks for recorded selections, answering from MLflow selection runs."""

    def __init__(self, by_stage: Mapping[str, dict[str, Any]]):
        self.by_stage = dict(by_stage)

    def selection(self, sweep: str, key: str, stage: str) -> dict[str, Any] | None:
        return self.by_stage.get(stage)


def selection_of(run) -> dict[str, Any] | None:
    """A selection run's recorded choice (its ``selected`` param), or None when unreadable."""
    raw = run.data.params.get("selected")
    try:
        selected = json.loads(raw) if raw else None
    except ValueError:
        return None
    if not isinstance(selected, list):
        return None
    return {"stage": run.data.tags.get(TAG_STAGE, ""), "selected": selected, "by": run.data.params.get("by", ""),
            "run_id": run.info.run_id}


def fetch_selections(client, experiment_ids: list[str], sweep: str, key: str | None) -> dict[str, dict[str, Any]]:
    """The latest recorded selection per stage of ``sweep`` (restricted to plan ``key`` when given): one query."""
    tags = {TAG_SWEEP: sweep, TAG_KIND: "selection"}
    if key is not None:
        tags[TAG_PLAN] = key
    out: dict[str, dict[str, Any]] = {}
    for run in search_runs(client, experiment_ids, tags, ["FINISHED"]):  # newest first
        sel = selection_of(run)
        if sel is not None and sel["stage"] and sel["stage"] not in out:
            out[sel["stage"]] = sel
    return out


def plan_view(cfg: Config, selections: Mapping[str, dict[str, Any]]) -> PlanView:
    """The config's plan with the given recorded selections (stage -> selection)."""
    stages = plan_stages(cfg, _RecordedSelections(selections), sweep=cfg.name)  # type: ignore[arg-type]
    by_stage: dict[str, list[Identity] | None] = {}
    keys: dict[Identity, str] = {}
    for sp in stages:
        if sp.cells is None:
            by_stage[sp.stage.name] = None
            continue
        ids = []
        for c in sp.cells:
            ident = identity_of(c)
            keys.setdefault(ident, c.key)
            ids.append(ident)
        by_stage[sp.stage.name] = ids
    return PlanView(by_stage, keys, staged=bool(cfg.stages), selections=dict(selections))


Combo = tuple[str, str, str]  # (arch, rot_loss, population)


def profile_plans(cfg: Config) -> dict[str, set[Combo]]:
    """Profile name -> the (arch, rot_loss, population) combinations its plan holds, for every profile of the
    config's file (cells of selecting stages are not known before their sweep and are not counted). A profile
    that does not load or plan here (e.g. its dataset is elsewhere) is left out."""
    if cfg.source == "<memory>" or not Path(cfg.source).is_file():
        return {}
    out: dict[str, set[Combo]] = {}
    for name in cfg.profiles:
        try:
            other = load_config(cfg.source, profile=name)
            plans = plan_stages(other, None, sweep=other.name)
        except BronchoError:
            continue
        out[name] = {(c.arch, c.rot_loss, c.population) for sp in plans for c in (sp.cells or [])}
    return out


def config_plan(client, experiment_ids: list[str], cfg: Config) -> PlanView:
    """The config's plan, selections read from MLflow (one query)."""
    return plan_view(cfg, fetch_selections(client, experiment_ids, cfg.name, plan_key(cfg)))
