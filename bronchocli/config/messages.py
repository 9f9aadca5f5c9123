"""The text of a config error: every problem at once, one line each, naming file:line, key path, value and rule.

A value may hold a URL with a password: every message is redacted before it is shown.
"""

from __future__ import annotations

import json
from typing import Any

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


def _describe(root: Any, error: dict[str, Any]) -> str:
    loc = tuple(error["loc"])
    if error["type"] == "extra_forbidden":
        allowed = _allowed_keys(root, loc)
        return f"unknown key {loc[-1]!r}" + (f" (allowed: {', '.join(allowed)})" if allowed else "")
    if error["type"] == "missing":
        return "required key is missing"
    value = error.get("input")
    shown = json.dumps(value, default=str) if not isinstance(value, dict) else "a mapping"
    msg = error["msg"]
    if error["type"] == "literal_error":
        msg = f"must be one of {error['ctx']['expected']}"
    return f"{shown}: {msg[0].lower() + msg[1:]}"


def format_errors(root: Any, exc: ValidationError, source: str, lines: dict[tuple, str]) -> str:
    """One message for a failed validation of ``root`` (the Config model): a line per problem, file:line first."""
    problems = []
    for error in exc.errors():
        loc = tuple(p for p in error["loc"] if not (isinstance(p, str) and p.startswith(("literal[", "list["))))
        error = {**error, "loc": loc}
        path = ".".join(str(p) if isinstance(p, str) else f"[{p}]" for p in loc).replace(".[", "[") or "<top>"
        where = next((lines[loc[:n]] for n in range(len(loc), -1, -1) if loc[:n] in lines), source)
        problems.append(f"{where}: {path}: {_describe(root, error)}")
    unique = list(dict.fromkeys(problems))
    if len(unique) == 1:  # one problem, one line
        return urls.redact(f"invalid config: {unique[0]}")  # a bad value may hold a URL password
    head = f"invalid config ({len(unique)} problems):"
    return urls.redact("\n".join([head, *("  " + p for p in unique)]))
