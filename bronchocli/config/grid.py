"""The plan's shape: the grid of cells, stages that select from earlier ones, and the cell key.

``expand_grid(cfg, patients)`` turns a ``Grid`` into frozen, hashable ``Cell``s whose ``key`` is a hash of
the cell and of every config section that changes what a run computes (``run_signature``), so the same
config gives the same key everywhere and a changed config gives new cells.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import re
from typing import TYPE_CHECKING, Any, Literal, Sequence

from pydantic import Field, field_validator

from .. import registry, runkeys
from ..cells import POPULATIONS, ArchName, Cell, Population, PoseFrame, RotLossName, Seed
from ..errors import ConfigError
from .sections import MAX_TRAJECTORIES, Section, _listify
from .spellings import speller_of, spelled

if TYPE_CHECKING:
    from .schema import Config

# An architecture registered now, written the common ways (``ConvLSTM``, ``conv-lstm``: convlstm)
ArchNameSpelled = spelled(ArchName, choices=registry.arch_names)
RotLossSpelled = spelled(RotLossName, choices=registry.rot_loss_names)  # a rotation loss registered now


class Grid(Section):
    arch: list[ArchNameSpelled] = Field(default_factory=lambda: list(registry.arch_names()))  # every one registered
    rot_loss: list[RotLossSpelled] = Field(default_factory=lambda: list(registry.rot_loss_names()))
    population: list[spelled(Population)] = list(POPULATIONS)
    folds: Literal["all"] | list[str] = "all"  # cross-subject held-out patients
    seed: list[Seed] = [0, 1, 2]
    pose_frame: list[spelled(PoseFrame)] = ["world"]
    train_trajectories: list[int | None] = [None]  # training trajectories per patient and lobe (None: splits.train)

    _wrap = field_validator("arch", "rot_loss", "population", "seed", "pose_frame", "folds", "train_trajectories",
                            mode="before")(lambda v: v if v == "all" else _listify(v))

    @field_validator("arch", "rot_loss", "population", "seed", "pose_frame", "train_trajectories")
    @classmethod
    def _not_empty(cls, v: list) -> list:
        if not v:
            raise ValueError("must list at least one value (an empty axis makes an empty grid)")
        if len(set(map(str, v))) != len(v):
            raise ValueError("lists a value twice")
        return v

    @field_validator("train_trajectories")
    @classmethod
    def _positive(cls, v: list) -> list:
        if any(n is not None and not 1 <= n <= MAX_TRAJECTORIES for n in v):
            raise ValueError(f"every value must be in [1, {MAX_TRAJECTORIES}] (or null for splits.train)")
        return v


SELECTABLE = ("arch", "rot_loss", "pose_frame", "train_trajectories")  # what a stage's "combination" can be


class Select(Section):
    """Which cells of an earlier stage go on: the ``top`` combinations by a validation metric (never a test one)."""

    top: int = Field(3, ge=1, le=1000)
    by: str = runkeys.val_best("pos_l2")  # a validation metric: val_best.loss or val_best.<m>, m validated (registry)
    over: list[spelled(Literal["arch", "rot_loss", "pose_frame", "train_trajectories"])] = ["arch", "rot_loss"]

    @field_validator("by")
    @classmethod
    def _validation_only(cls, v: str) -> str:
        if runkeys.val_best_name(v) is None:
            named = ", ".join(runkeys.val_best(m) for m in registry.metric_names(validation=True))
            raise ValueError(f"must be a validation metric ({named} or {runkeys.best_of(runkeys.VAL_LOSS)}): "
                             "selection never looks at test results")
        return v

    @field_validator("over")
    @classmethod
    def _over(cls, v: list) -> list:
        if not v or len(set(v)) != len(v):
            raise ValueError("must list one or more distinct cell fields")
        return v


class Stage(Section):
    """One step of a staged sweep (the paper's three experiments); docs/sweep.md."""

    name: str
    grid: dict[str, Any] = {}  # overrides of the top-level grid for this stage
    select: Select | None = None  # keep the top combinations of ``source`` (their other axes from this grid)
    source: str | None = None  # the stage ``select`` ranks (default: the previous stage)
    add: list[dict[str, Any]] = []  # extra combinations, e.g. {arch: offsetnet, rot_loss: mse}

    @field_validator("name")
    @classmethod
    def _stage_name(cls, v: str) -> str:
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_-]*", v):
            raise ValueError("must start with a letter or digit and use only letters, digits, '_', '-'")
        return v

    @field_validator("grid")
    @classmethod
    def _grid(cls, v: dict[str, Any]) -> dict[str, Any]:
        unknown = sorted(set(v) - set(Grid.model_fields))
        if unknown:
            raise ValueError(f"unknown grid key(s) {unknown} (allowed: {', '.join(Grid.model_fields)})")
        return v

    @field_validator("add")
    @classmethod
    def _add(cls, v: list[dict[str, Any]]) -> list[dict[str, Any]]:
        for entry in v:
            unknown = sorted(set(entry) - set(SELECTABLE))
            if unknown:
                raise ValueError(f"{entry}: unknown field(s) {unknown} (allowed: {', '.join(SELECTABLE)})")
        spellers = {f: speller_of(Grid.model_fields[f].annotation.__args__[0]) for f in SELECTABLE}
        # each value read the common ways (an unmatched one is refused with the cell's own message later)
        return [{k: (spellers[k].match(x) or x) if spellers[k] else x for k, x in entry.items()} for entry in v]

    def stage_grid(self, base: "Grid") -> "Grid":
        return Grid.model_validate({**base.model_dump(), **self.grid})


def decided_by_stages(stages: Sequence[Stage], field: str) -> dict[str, str]:
    """The stages that decide grid field ``field`` themselves, each with how (its own grid, its selection):
    the top-level ``grid.<field>`` does not reach their cells."""
    out = {}
    for st in stages:
        if field in st.grid:
            out[st.name] = f"its grid sets {field}"
        elif st.select is not None and field in st.select.over:
            out[st.name] = f"selected from stage {st.source}" if st.source else "selected from the previous stage"
    return out


def override_problem(stages: Sequence[Stage], key: str, text: str) -> tuple[str, bool]:
    """What a ``--set`` of ``grid.<field>`` (``text``) does under ``stages``: ("", _) when it applies to every
    stage; else the one line saying which stages decide the field themselves, and whether it reaches none."""
    parts = key.split(".")
    if not stages or parts[0] != "grid" or len(parts) != 2:
        return "", False
    decided = decided_by_stages(stages, parts[1])
    if not decided:
        return "", False
    how = "; ".join(f"{name}: {why}" for name, why in decided.items())
    if len(decided) == len(stages):
        return (f"--set {text}: has no effect: the stages decide the cells and every stage sets {parts[1]} itself "
                f"({how}); change the stages (experiments.yaml, or --set stages=[...]) or pick cells with "
                "--only", True)
    rest = ", ".join(st.name for st in stages if st.name not in decided)
    return (f"--set {text}: applies to stage(s) {rest} only; the others set {parts[1]} themselves ({how})", False)


# Sections that change what a run computes; runs, storage, tune, sweep (its launchers too) and
# profiles do not, so moving the MLflow store never invalidates finished cells.
RUN_SECTIONS = ("dataset", "splits", "data", "model", "train")


# Settings that change how fast a run goes, not what it computes.
NOT_IN_KEY = (("train", "threads"), ("train", "compile"), ("data", "workers"), ("data", "cache_dir"),
              ("data", "frames_on_device"), ("train", "speed_settings"))


def run_signature(cfg: Config) -> dict[str, Any]:
    data = cfg.model_dump(mode="json")
    sig = {k: data[k] for k in RUN_SECTIONS}
    for section, key in NOT_IN_KEY:
        sig[section].pop(key, None)
    return sig


def cell_key(cfg: Config, coords: dict[str, Any]) -> str:
    blob = json.dumps({"cell": coords, "config": run_signature(cfg)}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def expand_grid(cfg: Config, patients: Sequence[str] | None = None, grid: Grid | None = None) -> list[Cell]:
    """Every cell of ``grid`` (default ``cfg.grid``), in a stable order.

    ``patients`` (the dataset's patient ids) is needed when cross-subject folds
    are ``all``; listed folds must be among them when it is given.
    """
    g = grid or cfg.grid
    folds: list[str] = []
    if "cross-subject" in g.population:
        if g.folds == "all":
            if patients is None:
                raise ConfigError("grid.folds: 'all' needs the dataset's patient list (generate or point at a dataset first)")
            folds = list(patients)
        else:
            folds = list(g.folds)
            unknown = [f for f in folds if patients is not None and f not in patients]
            if unknown:
                raise ConfigError(f"grid.folds: {unknown} not in the dataset's patients ({', '.join(patients)})")
    out = []
    for population in g.population:
        for fold in (folds if population == "cross-subject" else [None]):
            for arch, rot_loss, size, seed, frame in itertools.product(g.arch, g.rot_loss, g.train_trajectories,
                                                                        g.seed, g.pose_frame):
                out.append(cfg.cell(arch=arch, rot_loss=rot_loss, population=population, fold=fold, seed=seed,
                                    pose_frame=frame, train_trajectories=size))
    return out


def stages_of(cfg: Config) -> list[Stage]:
    """The plan's stages: ``stages``, or one stage, its grid (docs/sweep.md)."""
    return list(cfg.stages) or [Stage(name="grid")]


def source_of(cfg: Config, stage: Stage) -> Stage:
    """The stage that ``stage`` selects from: its ``source``, else the one before it."""
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
