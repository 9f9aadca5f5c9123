"""Enum-like config values written the common ways, read as their one canonical value.

Every setting with a fixed set of values (``train.precision``, ``runs.model_artifact``, ``data.frames_on_device``,
the grid's axes, ...) is declared ``spelled(Literal[...])`` in ``sections.py`` / ``grid.py``: before pydantic checks
the value, ``Speller`` maps what a user may write onto the canonical choice:

* a number for a numeric choice: ``precision: 32`` (YAML reads it as a number) is ``"32"``;
* any case, ``_`` or a space for ``-``, surrounding blanks: ``BF16_Mixed`` is ``bf16-mixed``, ``Cross Subject`` is
  ``cross-subject``; when no choice matches, dashes dropped if that leaves exactly one (``conv-lstm`` is
  ``convlstm``);
* the usual other names of a value (``ALIASES``): ``fp32``/``32-true`` for ``32``, ``16``/``fp16``/``half`` for
  ``16-mixed``, ``bf16``/``bfloat16`` for ``bf16-mixed``, ``degrees`` for ``deg``, YAML's ``yes``/``no`` (read as
  true/false) for ``yes``/``no``, ...

A value that matches nothing is refused in one line naming the canonical choices and the accepted spellings
(``must be one of 'auto', '32', '16-mixed' or 'bf16-mixed' (also written: ...)``); the stored config always holds the
canonical value, so a run's params, the cell key and every consumer see one spelling.
"""

from __future__ import annotations

import types
from collections.abc import Callable, Sequence
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BeforeValidator
from pydantic_core import PydanticCustomError

# canonical value -> its other spellings (applied only where that canonical value is one of the setting's choices)
ALIASES: dict[str, tuple[Any, ...]] = {
    # train.precision (PyTorch Lightning's names included)
    "32": ("fp32", "float32", "32-true", "full", "single"),
    "16-mixed": ("16", "fp16", "float16", "half", "fp16-mixed", "mixed"),
    "bf16-mixed": ("bf16", "bfloat16", "bf16-true-mixed"),
    # runs.model_artifact
    "fp32": ("32", "float32", "full", "single"),
    "fp16": ("16", "float16", "half"),
    "none": (None, "no", "off", False),
    # data.frames_on_device (YAML 1.1 reads an unquoted yes/no as true/false)
    "yes": (True, "true", "on"),
    "no": (False, "false", "off"),
    # dataset.csv units and axes
    "deg": ("degree", "degrees"),
    "rad": ("radian", "radians"),
    "voxel": ("voxels", "vox"),
    "mm": ("millimetre", "millimetres", "millimeter", "millimeters"),
    "x": ("+x",), "y": ("+y",), "z": ("+z",),
    # grid.population
    "personalized": ("personalised",),
    # tune.space.*.type
    "int": ("integer",),
    "float": ("real",),
    "categorical": ("category", "choice"),
}


def _key(value: Any) -> str | None:
    """The comparable form of a written value: text lowered, ``_``/blanks as ``-``; a number as its digits."""
    if isinstance(value, bool) or value is None:
        return None
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return str(int(value)) if value.is_integer() else repr(value)
    if isinstance(value, str):
        return "-".join(value.strip().lower().replace("_", " ").split())
    return None


def _literals(tp: Any) -> tuple[list[str], list[Any]]:
    """The Literal choices inside ``tp`` (a Literal or a union holding one) and its other member types."""
    members = get_args(tp) if get_origin(tp) in (Union, types.UnionType) else (tp,)
    choices: list[str] = []
    others: list[Any] = []
    for m in members:
        if get_origin(m) is Literal:
            choices += [str(c) for c in get_args(m)]
        else:
            others.append(m)
    return choices, others


class Speller:
    """The before-validator of one enum-like setting: canonical value out, or a literal_error listing spellings."""

    def __init__(self, tp: Any, choices: Callable[[], Sequence[str]] | None = None):
        literal, self.others = _literals(tp)
        self._choices = choices or (lambda: literal)
        self.takes_bool = bool in self.others
        self.passes_others = any(o not in (bool, type(None)) for o in self.others)  # e.g. folds: 'all' | [names]

    def choices(self) -> list[str]:
        return list(self._choices())

    def spellings(self, choices: Sequence[str]) -> list[str]:
        """Other accepted ways of writing these choices, for the error message."""
        out = [f"{c} as a number" for c in choices if c.isdigit()]
        for c in choices:  # the two commonest other names of each choice (the rest are in ALIASES)
            names = [a for a in ALIASES.get(c, ()) if isinstance(a, str) and a not in choices and a not in out]
            out += names[:2]
        return out

    def match(self, value: Any) -> str | None:
        choices = self.choices()
        if isinstance(value, str) and value in choices:
            return value
        for c in choices:  # an alias that is not text (YAML's true/false/null)
            if any(a is value or (type(a) is type(value) and a == value) for a in ALIASES.get(c, ())
                   if a is None or isinstance(a, bool)):
                return c
        key = _key(value)
        if key is None:
            return None
        forms = {c: {_key(c), *(_key(a) for a in ALIASES.get(c, ()))} - {None} for c in choices}
        hits = [c for c, f in forms.items() if key in f]
        if len(hits) == 1:
            return hits[0]
        bare = key.replace("-", "")
        hits = [c for c, f in forms.items() if bare in {k.replace("-", "") for k in f}]
        return hits[0] if len(hits) == 1 and not key.startswith("-") else None

    def __call__(self, value: Any) -> Any:
        if isinstance(value, bool) and self.takes_bool:
            return value
        found = self.match(value)
        if found is not None:
            return found
        if self.passes_others and not isinstance(value, (str, int, float)):
            return value  # a list where a list is allowed: its own type checks it
        choices = self.choices()
        shown = [repr(c) for c in choices] + (["true", "false"] if self.takes_bool else [])
        expected = f"{', '.join(shown[:-1])} or {shown[-1]}" if len(shown) > 1 else "".join(shown)
        also = self.spellings(choices)
        how = "any case, '_' for '-'" if any("-" in c for c in choices) else "any case"
        expected += f" (also written: {', '.join(also)}, ...; {how})" if also else f" ({how})"
        raise PydanticCustomError("literal_error", "Input should be {expected}", {"expected": expected})


def spelled(tp: Any, choices: Callable[[], Sequence[str]] | None = None) -> Any:
    """``tp`` (a Literal, or a union holding one) read the common ways (module docstring); ``choices``: the
    choices when they are known only at validation time (registered architectures)."""
    return Annotated[tp, BeforeValidator(Speller(tp, choices))]


def speller_of(annotation: Any) -> Speller | None:
    """The ``Speller`` a field's annotation carries (None: not an enum-like setting); for tests and docs."""
    for meta in getattr(annotation, "__metadata__", ()):
        func = getattr(meta, "func", None)
        if isinstance(func, Speller):
            return func
    return None
