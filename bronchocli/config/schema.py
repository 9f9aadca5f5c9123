"""The whole experiments.yaml: the ``Config`` model, its validation, and what ``tune.space`` may search.

``validate(raw, ...)`` is the one way a config comes to exist (loading, ``with_values``, tuning), so every
config in the program has passed the same checks and has its paths resolved (``cfg.paths``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml
from pydantic import PrivateAttr, ValidationError, field_validator, model_validator

from .. import cells, urls
from ..cells import Cell
from ..errors import ConfigError
from .grid import Grid, Stage, cell_key
from .messages import format_errors
from .paths import Paths
from .sections import (
    DataCfg,
    DatasetCfg,
    EvalCfg,
    ModelCfg,
    RunsCfg,
    Section,
    Splits,
    Storage,
    SweepCfg,
    Train,
    Tune,
)


class Config(Section):
    name: str
    runs: RunsCfg = RunsCfg()
    storage: Storage = Storage()
    dataset: DatasetCfg = DatasetCfg()
    splits: Splits = Splits()
    grid: Grid = Grid()
    stages: list[Stage] = []  # a staged plan (the paper's protocol); empty: run ``grid`` as one stage
    data: DataCfg = DataCfg()
    model: ModelCfg = ModelCfg()
    train: Train = Train()
    eval: EvalCfg = EvalCfg()
    tune: Tune = Tune()
    sweep: SweepCfg = SweepCfg()
    profiles: dict[str, dict[str, Any]] = {}

    _paths: Paths | None = PrivateAttr(default=None)
    _source: str = PrivateAttr(default="<memory>")
    _lines: dict[tuple, str] = PrivateAttr(default_factory=dict)  # key path -> file:line, for later errors
    _profile: str | None = PrivateAttr(default=None)

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", v):
            raise ValueError("must start with a letter or digit and use only letters, digits, '.', '_', '-'")
        return v

    @model_validator(mode="after")
    def _stages(self) -> "Config":
        names = [st.name for st in self.stages]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"stages: stage name(s) {dupes} used twice")
        for i, st in enumerate(self.stages):
            try:
                st.stage_grid(self.grid)
            except ValidationError as exc:
                first = exc.errors()[0]
                raise ValueError(f"stages[{i}] ({st.name}).grid.{'.'.join(map(str, first['loc']))}: {first['msg']}"
                                 ) from None
            if st.source is not None and st.source not in names[:i]:
                raise ValueError(f"stages[{i}] ({st.name}).source {st.source!r}: must name an earlier stage "
                                 f"({', '.join(names[:i]) or 'none before it'})")
            if st.select is not None and i == 0:
                raise ValueError(f"stages[0] ({st.name}).select: the first stage has no earlier stage to select from")
        return self

    @property
    def paths(self) -> Paths:
        """Every path and URL, resolved against the config file's folder when it was loaded."""
        if self._paths is None:
            self._paths = Paths.of(self, Path.cwd())
        return self._paths

    @property
    def profile(self) -> str | None:
        return self._profile

    @property
    def source(self) -> str:
        """The file the config was read from ("<memory>" for one built in code)."""
        return self._source

    @property
    def experiment_name(self) -> str:
        return self.runs.experiment or self.name

    def cell(self, **coords: Any) -> Cell:
        """A validated cell of this config, with its key (ConfigError naming the bad field otherwise).

        No ``pose_frame`` (or None): the first of ``grid.pose_frame``, the frame the config's plan trains in.
        """
        if coords.get("pose_frame") is None:
            coords["pose_frame"] = self.grid.pose_frame[0]
        bare = cells.make(**coords)
        return bare.model_copy(update={"key": cell_key(self, bare.coords())})

    def dump(self) -> dict[str, Any]:
        """The resolved config as plain data (profiles dropped: they are already applied)."""
        data = self.model_dump(mode="json")
        data.pop("profiles")
        return data

    def to_yaml(self) -> str:
        """The config as YAML, every URL password shown as ``***``."""
        return urls.redact(yaml.safe_dump(self.dump(), sort_keys=False))

    def launcher_settings(self, name: str, model: type[Section]) -> Section:
        """``sweep.launchers.<name>`` validated against ``model`` (the launcher's own settings; its defaults when
        the section is absent): a ConfigError naming ``sweep.launchers.<name>.<key>``, its value and what is
        allowed, one line per problem."""
        raw = self.sweep.launchers.get(name) or {}
        try:
            return model.model_validate(raw)
        except ValidationError as exc:
            raise ConfigError(format_errors(model, exc, self._source, self._lines,
                                            prefix=("sweep", "launchers", name))) from None

    def with_values(self, values: dict[str, Any]) -> "Config":
        """A validated copy with dotted-path values set, e.g. ``{"train.lr": 1e-3}``."""
        raw = self.model_dump(mode="json")
        for key, value in values.items():
            set_path(raw, key, value, where=f"override {key}")
        space = any(k == "tune" or k.startswith("tune.space") for k in values)  # else checked when it loaded
        return validate(raw, self._source, {}, self.paths.base, self._profile, space=space)


TUNABLE = ("data", "model", "train", "splits", "dataset")  # the sections ``tune.space`` may search


def space_problems(cfg: Config) -> list[str]:
    """What is wrong with ``tune.space``: each key a settable run setting, each distribution well formed."""
    problems = []
    for path, p in cfg.tune.space.items():
        where = f"tune.space.{path}"
        if path.split(".")[0] not in TUNABLE:
            problems.append(f"{where}: only run settings can be tuned ({', '.join(TUNABLE)})")
            continue
        if p.type == "categorical" and not p.choices:
            problems.append(f"{where}: categorical needs a non-empty 'choices' list")
            continue
        if p.type != "categorical" and (p.low is None or p.high is None or not p.low < p.high):
            problems.append(f"{where}: {p.type} needs low < high (got low={p.low}, high={p.high})")
            continue
        if p.log and p.type != "categorical" and p.low <= 0:
            problems.append(f"{where}: log scale needs low > 0 (got {p.low})")
            continue
        if p.step is not None and not 0 < p.step <= p.high - p.low:  # a bigger step leaves one value to search
            problems.append(f"{where}: step {p.step:g} outside its range (0, high - low] = (0, {p.high - p.low:g}]")
            continue
        probes = p.choices if p.type == "categorical" else [p.low, p.high]
        for value in probes:  # every choice (and both ends of a range) must be a valid value of the setting
            value = int(value) if p.type == "int" else value
            raw = cfg.model_dump(mode="json")
            try:
                set_path(raw, path, value, where=where)
                validate(raw, cfg._source, {}, cfg.paths.base, cfg._profile, space=False)
            except ConfigError as exc:
                last = str(exc).splitlines()[-1].strip().removeprefix("invalid config: ")
                problems.append(f"{where}: {last.partition(': ')[2] or last}")
                break
    return problems or enqueue_problems(cfg)


def _outside(p: TuneParam, value: Any, key: str) -> str | None:
    """Why an enqueued ``value`` is no value a trial of ``tune.space.<key>`` (``p``) takes (None: it is)."""
    if p.type == "categorical":
        return None if value in (p.choices or []) else f"must be one of tune.space.{key}'s choices " \
            f"({', '.join(map(repr, p.choices or []))}): Optuna refuses any other"
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if p.type == "int" and not (number and float(value).is_integer()):
        return f"must be a whole number (tune.space.{key} is an int)"
    if not number or not p.low <= value <= p.high:
        return f"must be a number within tune.space.{key}'s range [{p.low:g}, {p.high:g}]"
    return None


def enqueue_problems(cfg: Config) -> list[str]:
    """What a trial of ``tune.enqueue`` would meet: each value one its ``tune.space`` distribution takes, and the
    trial's config (the base config with those values) valid, so a bad recipe fails at load, not as a trial."""
    problems = []
    for i, params in enumerate(cfg.tune.enqueue):
        where = f"tune.enqueue[{i}]"
        bad = [f"{where}.{key}: {value!r}: {why}" for key, value in params.items()
               if key in cfg.tune.space and (why := _outside(cfg.tune.space[key], value, key)) is not None]
        if bad:
            problems += bad
            continue
        raw = cfg.model_dump(mode="json")
        try:
            for key, value in params.items():
                set_path(raw, key, value, where=f"{where}.{key}")
            validate(raw, cfg._source, {}, cfg.paths.base, cfg._profile, space=False)
        except ConfigError as exc:
            last = str(exc).splitlines()[-1].strip().removeprefix("invalid config: ")
            problems.append(f"{where} (trial {i}): {last.partition(': ')[2] or last}")
    return problems


# -- loading ------------------------------------------------------------------

def set_path(data: dict[str, Any], dotted: str, value: Any, where: str) -> None:
    parts = dotted.split(".")
    node = data
    for part in parts[:-1]:
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        if not isinstance(child, dict):
            raise ConfigError(f"{where}: '{part}' in '{dotted}' is a value, not a section")
        node = child
    node[parts[-1]] = value


def validate(raw: dict[str, Any], source: str, lines: dict[tuple, str], base: Path, profile: str | None,
              space: bool = True) -> Config:
    try:
        cfg = Config.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(format_errors(Config, exc, source, lines)) from None
    cfg._source, cfg._profile, cfg._lines = source, profile, dict(lines)
    cfg._paths = Paths.of(cfg, base)
    problems = space_problems(cfg) if space else []
    if problems:  # the same check as `tune`, so `config` never calls a space valid that tune refuses
        def where(problem: str) -> str:  # the line of tune.enqueue or tune.space
            part = "enqueue" if problem.startswith("tune.enqueue") else "space"
            return next((v for k, v in lines.items() if k[:2] == ("tune", part)), source)
        shown = [f"{where(p)}: {p}" for p in problems]
        raise ConfigError(urls.redact(f"invalid config: {shown[0]}" if len(shown) == 1 else
                                      "\n".join([f"invalid config ({len(shown)} problems):",
                                                  *("  " + p for p in shown)])))
    return cfg
