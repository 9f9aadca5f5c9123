"""The one cell type: what a single training run is (architecture, loss, population, fold, seed, ...).

A :class:`Cell` is validated where it is made, whether from the grid, a
command's flags, MLflow tags or a ``--only`` filter, so a bad value is one
line naming the field and the allowed values, before any work starts. Its
``key`` (a hash of the coordinates and of the run-defining config, see
``config.cell_key``) identifies it in the sweep table and in MLflow.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Annotated, Any, Literal, get_args

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import PydanticCustomError

from . import registry
from .errors import ConfigError


def _registered(kind: str, names: Callable[[], tuple[str, ...]]) -> BeforeValidator:
    """A value registered now (registry.py), refused in the words pydantic uses for a Literal."""

    def check(value: Any) -> Any:
        allowed = names()
        if value not in allowed:
            shown = [repr(n) for n in allowed]
            raise PydanticCustomError("literal_error", "Input should be {expected}",
                                      {"expected": f"{', '.join(shown[:-1])} or {shown[-1]}" if len(shown) > 1
                                       else "".join(shown)})
        return value

    check.__name__ = f"registered_{kind}"
    return BeforeValidator(check)


# A cell's architecture / rotation loss: any name registered in registry.py when the value is checked.
ArchName = Annotated[str, _registered("arch", registry.arch_names)]
RotLossName = Annotated[str, _registered("rot_loss", registry.rot_loss_names)]
# The same as Literals, for the CLI's --arch / --rot-loss choices (--help lists them, the shell completes them).
Arch = Literal[registry.arch_names()]  # type: ignore[valid-type]
RotLoss = Literal[registry.rot_loss_names()]  # type: ignore[valid-type]
Population = Literal["personalized", "cross-subject"]
PoseFrame = Literal["world", "camera"]
Lobe = Literal["ur", "br", "ul", "bl"]

POPULATIONS: tuple[str, ...] = get_args(Population)
POSE_FRAMES: tuple[str, ...] = get_args(PoseFrame)
LOBES: tuple[str, ...] = get_args(Lobe)

# A random seed: numpy's legacy seeding (and so the whole stack) takes 0 .. 2**32 - 1.
SEED_MAX = 2**32 - 1
Seed = Annotated[int, Field(ge=0, le=SEED_MAX)]

# The coordinates of a cell, in label order; also its MLflow tags and the ``--only`` keys.
FIELDS: tuple[str, ...] = ("arch", "rot_loss", "population", "fold", "seed", "pose_frame", "train_trajectories")


class Cell(BaseModel):
    """One run of a sweep. ``train_trajectories`` None: the split's own training set (``splits.train``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    arch: ArchName
    rot_loss: RotLossName
    population: Population
    fold: str | None = None  # held-out patient (cross-subject only)
    seed: Seed = 0
    pose_frame: PoseFrame = "world"
    train_trajectories: int | None = Field(None, ge=1)  # training trajectories per patient and lobe
    key: str = ""  # set by config.Config.cell(); empty for a bare coordinate

    @model_validator(mode="after")
    def _fold(self) -> Cell:
        if self.population == "cross-subject" and not self.fold:
            raise ValueError("fold: cross-subject needs the held-out patient (e.g. fold p00)")
        if self.population == "personalized" and self.fold:
            raise ValueError(f"fold {self.fold!r}: only cross-subject cells have a held-out patient")
        return self

    @property
    def label(self) -> str:
        parts = [self.arch, self.rot_loss, self.population + (f"/{self.fold}" if self.fold else ""),
                 f"s{self.seed}", self.pose_frame]
        if self.train_trajectories is not None:
            parts.append(f"t{self.train_trajectories}")
        return "/".join(parts)

    def coords(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in FIELDS}

    def tags(self) -> dict[str, str]:
        """The coordinates as MLflow tag values (None -> empty string)."""
        return {k: "" if v is None else str(v) for k, v in self.coords().items()}

    @classmethod
    def from_tags(cls, tags: Mapping[str, str], key_tag: str = "cell_key") -> Cell:
        """The cell an MLflow run was made for (ConfigError when its tags are not a valid cell)."""
        raw: dict[str, Any] = {k: tags.get(k) or None for k in FIELDS}
        return make(**raw, key=tags.get(key_tag, "") or "")


class TrialCell(Cell):
    """A claims row of a tuning study (``sweep.tuning.launch``): trial slot ``trial`` of the study's target cell, whose
    coordinates it carries. Its key is the slot's (``trial-0007``), its label ``trial 7 · <the cell's label>``."""

    trial: int = Field(ge=0)

    @property
    def label(self) -> str:
        return f"trial {self.trial} · {super().label}"

    def coords(self) -> dict[str, Any]:
        return {**super().coords(), "trial": self.trial}

    def target(self) -> Cell:
        """The study's target cell (its coordinates, no key)."""
        return Cell(**super().coords())


def choices() -> dict[str, tuple[str, ...]]:
    """The allowed values of each field that has a fixed set (architectures, rotation losses: those registered
    now)."""
    return {"arch": registry.arch_names(), "rot_loss": registry.rot_loss_names(), "population": POPULATIONS,
            "pose_frame": POSE_FRAMES}


def _problem(error: dict[str, Any]) -> str:
    field = ".".join(str(p) for p in error["loc"]) or "cell"
    value = error.get("input")
    allowed = choices()
    if error["type"] == "literal_error" and field in allowed:
        return f"{field} {value!r}: must be one of {', '.join(allowed[field])}"
    msg = error["msg"].removeprefix("Value error, ")
    if error["type"] == "value_error":
        return msg
    return f"{field} {value!r}: {msg[0].lower() + msg[1:]}"


def make(**values: Any) -> Cell:
    """A validated cell; ConfigError with one line per bad field otherwise."""
    if values.get("train_trajectories") is not None:
        values["train_trajectories"] = _int(values["train_trajectories"], "train_trajectories")
    if values.get("seed") is not None:
        values["seed"] = _int(values["seed"], "seed")
    else:
        values.pop("seed", None)
    if values.get("pose_frame") is None:
        values.pop("pose_frame", None)
    if "trial" in values:  # a tuning study's trial slot (a claims row of its study)
        values["trial"] = _int(values["trial"], "trial")
    try:
        return TrialCell(**values) if "trial" in values else Cell(**values)
    except ValidationError as exc:
        raise ConfigError("; ".join(dict.fromkeys(_problem(e) for e in exc.errors()))) from None


def _int(value: Any, field: str) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{field} {value!r}: must be an integer") from None


# -- selecting cells (``--only``) ---------------------------------------------------------------

Selection = dict[str, set[str]]


def parse_only(specs: Iterable[str] | None) -> Selection:
    """``["arch=lstm,conv3d;population=personalized", "seed=0"]`` -> ``{"arch": {...}, ...}`` (keys ANDed).

    Each value is checked like a cell field, so a typo is caught before any cell is planned.
    """
    out: Selection = {}
    for spec in specs or []:
        if not spec.strip(" ;"):  # an empty --only would select every cell: never what was meant
            raise ConfigError(f"--only {spec!r}: empty; expected key=value[,value...] with key one of "
                              f"{', '.join(FIELDS)} (leave --only out to run every cell)")
        for part in filter(None, (p.strip() for p in spec.split(";"))):
            key, sep, values = part.partition("=")
            key = key.strip().replace("-", "_")
            if not sep or key not in FIELDS:
                raise ConfigError(f"--only {part!r}: expected key=value[,value...] with key one of "
                                  f"{', '.join(FIELDS)}")
            vals = {v.strip() for v in values.split(",") if v.strip()}
            if not vals:
                raise ConfigError(f"--only {part!r}: no values given")
            for v in vals:
                _check_value(key, v, part)
            out[key] = out[key] & vals if key in out else vals
    return out


def _check_value(key: str, value: str, part: str) -> None:
    allowed = choices()
    if key in allowed and value not in allowed[key]:
        raise ConfigError(f"--only {part!r}: {key} {value!r} must be one of {', '.join(allowed[key])}")
    if key in ("seed", "train_trajectories"):
        _int(value, key)


def select(cells: Sequence[Cell], only: Selection) -> list[Cell]:
    """Cells matching every key of ``only``; a value no cell has is an error (likely a typo)."""
    for key, vals in only.items():
        known = {c.tags()[key] for c in cells}
        unknown = sorted(vals - known)
        if unknown:
            shown = ", ".join(sorted(v for v in known if v)) or "none"
            raise ConfigError(f"--only {key}={','.join(unknown)}: no cell of the plan has that {key} (it has: {shown})")
    return [c for c in cells if all(c.tags()[k] in v for k, v in only.items())]
