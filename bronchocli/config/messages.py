"""The text of a config error: every problem at once, one line each, naming file:line, key path, value and rule.

A value may hold a URL with a password: every message is redacted before it is shown.
"""

from __future__ import annotations

import json
from typing import Any, get_args

from pydantic import ValidationError

from .. import urls


def _allowed_keys(root: Any, loc: tuple) -> list[str]:
    model: Any = root
    for part in loc[:-1]:
        field = getattr(model, "model_fields", {}).get(part)
        if field is None:
            return []
        model = field.annotation
    return sorted(getattr(model, "model_fields", {}))


BOUND_ERRORS = ("greater_than", "greater_than_equal", "less_than", "less_than_equal")


def _constraints(annotation: Any, metadata: list[Any]) -> dict[str, Any]:
    """ge/gt/le/lt of a field: its own metadata, else that of the ``Annotated`` item type of a list (``list[Seed]``)."""
    found = {k: getattr(m, k) for m in metadata for k in ("ge", "gt", "le", "lt") if getattr(m, k, None) is not None}
    if found:
        return found
    for arg in get_args(annotation):
        inner = list(getattr(arg, "__metadata__", ()))
        inner += [c for m in inner for c in getattr(m, "metadata", ())]  # Field(ge=...) inside Annotated
        found = _constraints(arg, inner)
        if found:
            return found
    return {}


def allowed_range(root: Any, loc: tuple) -> str | None:
    """The documented range of the numeric setting at ``loc`` in interval notation, e.g. ``[1, 10000000]``,
    ``(0, 10]``, ``[0, ∞)``; None when it has no bounds (or ``loc`` is not a setting)."""
    model: Any = root
    field = None
    for part in (p for p in loc if isinstance(p, str)):
        field = getattr(model, "model_fields", {}).get(part)
        if field is None:
            return None
        model = field.annotation
    if field is None:
        return None
    c = _constraints(field.annotation, list(field.metadata))
    if not c:
        return None
    def num(v: float) -> str:
        return str(int(v)) if float(v).is_integer() else repr(v)

    low = f"[{num(c['ge'])}" if "ge" in c else f"({num(c['gt'])}" if "gt" in c else "(-∞"
    high = f"{num(c['le'])}]" if "le" in c else f"{num(c['lt'])})" if "lt" in c else "∞)"
    return f"{low}, {high}"


def _describe(root: Any, error: dict[str, Any]) -> str:
    loc = tuple(error["loc"])
    if error["type"] == "extra_forbidden":
        allowed = _allowed_keys(root, loc)
        return f"unknown key {loc[-1]!r}" + (f" (allowed: {', '.join(allowed)})" if allowed else "")
    if error["type"] == "missing":
        return "required key is missing"
    value = error.get("input")
    msg = error["msg"]
    if isinstance(value, dict) and error["type"] == "value_error":  # a section's own check: its reason is the line
        return msg.removeprefix("Value error, ")
    shown = json.dumps(value, default=str) if not isinstance(value, dict) else "a mapping"
    if error["type"] == "literal_error":
        msg = f"must be one of {error['ctx']['expected']}"
    if error["type"] in BOUND_ERRORS and (allowed := allowed_range(root, loc)) is not None:
        msg += f" (allowed range {allowed})"
    return f"{shown}: {msg[0].lower() + msg[1:]}"


def format_errors(root: Any, exc: ValidationError, source: str, lines: dict[tuple, str], prefix: tuple = ()) -> str:
    """One message for a failed validation of ``root`` (the Config model, or the model of the section at ``prefix``:
    a launcher's ``sweep.launchers.<name>``): a line per problem, file:line first."""
    problems = []
    for error in exc.errors():
        loc = tuple(p for p in error["loc"] if not (isinstance(p, str) and p.startswith(("literal[", "list["))))
        error = {**error, "loc": loc}
        full = prefix + loc
        path = ".".join(str(p) if isinstance(p, str) else f"[{p}]" for p in full).replace(".[", "[") or "<top>"
        where = next((lines[full[:n]] for n in range(len(full), -1, -1) if full[:n] in lines), source)
        problems.append(f"{where}: {path}: {_describe(root, error)}")
    unique = list(dict.fromkeys(problems))
    if len(unique) == 1:  # one problem, one line
        return urls.redact(f"invalid config: {unique[0]}")  # a bad value may hold a URL password
    head = f"invalid config ({len(unique)} problems):"
    return urls.redact("\n".join([head, *("  " + p for p in unique)]))
