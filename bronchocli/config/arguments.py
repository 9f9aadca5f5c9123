"""The rules of the commands' arguments, one definition for the command line and the Python API.

A rule says what an argument must be (an integer, a number, a string, a sequence of strings) and its range.
The commands' options take their bounds from here (``bounds``: Typer's ``min``/``max``), and every public call
of ``bronchocli.api`` checks what it was given against the same rules at its boundary (``checked``), so
``api.sweep(workers="2")`` or ``api.train(seed=1.5)`` is one :class:`ArgumentError` naming the argument, as
``--workers 2x`` or ``--seed 1.5`` is one line on the command line, never a failure deep inside.
"""

from __future__ import annotations

import functools
import inspect
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from ..errors import BronchoError
from .sections import MAX_WORKERS


class ArgumentError(BronchoError):
    """An argument of a public call of the wrong type or out of its range (named, with what is allowed)."""


@dataclass(frozen=True)
class Rule:
    """``flag``: the command line's spelling; ``kind``: int, float, str, bool, "path" or "strings" (a sequence of
    strings, never one string); ``low``/``high``: the inclusive range of a number."""

    flag: str
    kind: Any
    low: float | None = None
    high: float | None = None

    def bounds(self) -> dict[str, Any]:
        """Typer's ``min``/``max`` of the option."""
        return {k: v for k, v in (("min", self.low), ("max", self.high)) if v is not None}

    def allowed(self) -> str:
        what = {int: "an integer", float: "a number", str: "a string", bool: "True or False", "path": "a path",
                "strings": "a list of strings (not one string)"}[self.kind]
        if self.low is not None and self.high is not None:
            return f"{what} from {self.low:g} to {self.high:g}"
        if self.low is not None:
            return f"{what} >= {self.low:g}"
        return what

    def ok(self, value: Any) -> bool:
        if self.kind is int:
            good = isinstance(value, int) and not isinstance(value, bool)
        elif self.kind is float:
            good = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        elif self.kind == "strings":
            good = (isinstance(value, Sequence) and not isinstance(value, (str, bytes))
                    and all(isinstance(v, str) for v in value))
        elif self.kind == "path":
            good = isinstance(value, (str, os.PathLike))
        else:
            good = isinstance(value, self.kind)
        if not good or self.kind not in (int, float):
            return good
        return (self.low is None or value >= self.low) and (self.high is None or value <= self.high)


RULES: dict[str, Rule] = {
    # where the work runs
    "workers": Rule("--workers", int, 1, MAX_WORKERS),
    "per_gpu": Rule("--per-gpu", int, 1),
    "gpus": Rule("--gpus", str),
    "launcher": Rule("--launcher", str),
    "storage": Rule("--storage", str),
    "detach": Rule("--detach", bool),
    "retry_failed": Rule("--retry-failed", bool),
    "runner": Rule("--runner", str),
    # the cell
    "arch": Rule("--arch", str),
    "rot_loss": Rule("--rot-loss", str),
    "population": Rule("--population", str),
    "fold": Rule("--fold", str),
    "seed": Rule("--seed", int),
    "pose_frame": Rule("--pose-frame", str),
    "train_trajectories": Rule("--train-trajectories", int, 1),
    # the config
    "profile": Rule("--profile", str),
    "overrides": Rule("--set", "strings"),
    "only": Rule("--only", "strings"),
    "use_tuned": Rule("--use-tuned", str),
    # training and tuning
    "again": Rule("--again", bool),
    "trials": Rule("--trials", int, 1),
    "timeout": Rule("--timeout", float, 0.001),
    "study": Rule("--study", str),
    "name": Rule("--study", str),
    # reading
    "sweep": Rule("--sweep", str),
    "show_all": Rule("--all", bool),
    "repair": Rule("--repair", bool),
    "best": Rule("--best", int, 0),
    "trajectories": Rule("--trajectories", int, 1),
    "table": Rule("--table", str),
    "evaluation": Rule("--eval", str),
    "fmt": Rule("--format", str),
    "out": Rule("--out", "path"),
}


def check(call: str, values: dict[str, Any]) -> None:
    """Every ruled argument of ``values`` that is given (not None) as its rule says, else one ArgumentError."""
    for name, value in values.items():
        rule = RULES.get(name)
        if rule is None or value is None or rule.ok(value):
            continue
        raise ArgumentError(f"{call}: {name}={value!r}: must be {rule.allowed()} (as {rule.flag} on the command "
                            "line)")


F = TypeVar("F", bound=Callable[..., Any])


def checked(fn: F) -> F:
    """``fn`` checking its arguments against ``RULES`` before it runs (``api.<name>: <arg>=<value>: must be …``);
    those of its ``**keywords`` (a launcher's options) too."""
    signature = inspect.signature(fn)
    call = f"api.{fn.__name__}"
    keywords = [p.name for p in signature.parameters.values() if p.kind is p.VAR_KEYWORD]

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            bound = signature.bind(*args, **kwargs)
        except TypeError as exc:
            raise ArgumentError(f"{call}: {exc}") from None
        values = dict(bound.arguments)
        for name in keywords:
            values.update(values.pop(name, {}))
        check(call, values)
        return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
