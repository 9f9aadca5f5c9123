"""Reading experiments.yaml: YAML with line numbers, profiles, ``--set`` overrides.

``load_config(path, profile, overrides)`` reads the YAML (duplicate keys, recursive aliases and alias bombs
refused, naming the line), deep-merges the named profile over it, applies ``--set key.path=value``
overrides, and validates the result (``schema.validate``): every problem in one ``ConfigError`` naming
file, line, key path, the bad value and what is allowed.
"""

from __future__ import annotations

import copy
import logging
import os
import re
from pathlib import Path
from typing import Any, Sequence

import yaml

from .. import pathcheck, urls
from ..errors import ConfigError
from .grid import override_problem
from .schema import Config, set_path, validate

DEFAULT_CONFIG = "experiments.yaml"
log = logging.getLogger(__name__)

def parse_override(text: str) -> tuple[str, Any]:
    """``key.path=value`` -> (path, YAML-parsed value)."""
    key, sep, raw = text.partition("=")
    if not sep or not re.fullmatch(r"[A-Za-z_][\w-]*(\.[\w-]+)*", key.strip()):
        raise ConfigError(urls.redact(f"--set {text!r}: expected key.path=value, e.g. --set train.lr=3e-4"))
    try:
        _check_structure(yaml.compose(raw, Loader=_UniqueKeyLoader), f"--set {key.strip()}")  # noqa: S506
        value = yaml.load(raw, Loader=_UniqueKeyLoader) if raw.strip() else None  # noqa: S506 - SafeLoader
    except _DuplicateKey as exc:
        raise ConfigError(urls.redact(f"--set {text!r}: duplicate key {exc.key!r}")) from None
    except yaml.YAMLError:
        value = raw
    return key.strip(), value


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def _line_index(node: yaml.Node, source: str, prefix: tuple = ()) -> dict[tuple, str]:
    """Key path -> ``file:line`` where it is written, from a composed YAML node tree."""
    where = {prefix: f"{source}:{node.start_mark.line + 1}"}
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            where.update(_line_index(value_node, source, prefix + (str(key_node.value),)))
            where[prefix + (str(key_node.value),)] = f"{source}:{key_node.start_mark.line + 1}"
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            where.update(_line_index(item, source, prefix + (i,)))
    return where


class _DuplicateKey(yaml.YAMLError):
    def __init__(self, key: Any, line: int, first: int):
        super().__init__(f"duplicate key {key!r}")
        self.key, self.line, self.first = key, line, first


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, except that a key written twice in one mapping is an error (PyYAML keeps the last),
    in block and flow style alike, and ``1e-5`` is a number (YAML 1.2; PyYAML's 1.1 rules read it as text)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, tuple[int, int]] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # ``<<: *anchor`` may repeat and is overridden by design
                continue
            key = self.construct_object(key_node, deep=True)
            mark = key_node.start_mark
            try:
                first = seen.setdefault(key, (mark.index, mark.line + 1))
            except TypeError:  # an unhashable key: the base class reports it
                continue
            if first[0] != mark.index:  # the position, not the line: ``{lr: 1, lr: 2}`` is one line
                raise _DuplicateKey(key, mark.line + 1, first[1])
        return super().construct_mapping(node, deep)


_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))

MAX_YAML_VALUES = 100_000  # a config past this many values (after aliases expand) is an alias bomb, not a config


def _check_structure(node: yaml.Node | None, source: str) -> None:
    """Refuse a recursive alias (an anchor used inside itself) and an alias bomb, naming the line."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(n: yaml.Node) -> int:
        if id(n) in sizes:
            return sizes[id(n)]
        if id(n) in active:
            raise ConfigError(f"{source}:{n.start_mark.line + 1}: recursive YAML alias (an anchor used inside "
                              "itself); write the values out instead")
        active.add(id(n))
        children = ([c for pair in n.value for c in pair] if isinstance(n, yaml.MappingNode) else
                    list(n.value) if isinstance(n, yaml.SequenceNode) else [])
        total = 1 + sum(size(c) for c in children)
        active.discard(id(n))
        if total > MAX_YAML_VALUES:
            raise ConfigError(f"{source}:{n.start_mark.line + 1}: YAML aliases expand to more than "
                              f"{MAX_YAML_VALUES:,} values; a config this large is not a config")
        sizes[id(n)] = total
        return total

    if node is not None:
        size(node)


def _read_text(path: Path) -> str:
    pathcheck.resolve(path, "config file")  # a symlink loop: one line, not "not found"
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the config ({exc.strerror or exc})") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(f"{path}:{line}: not UTF-8 text (byte 0x{raw[exc.start]:02x}); save the config as "
                          "UTF-8") from None


def _read_yaml(path: Path) -> tuple[dict[str, Any], dict[tuple, str]]:
    text = _read_text(path)
    try:
        node = yaml.compose(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
        _check_structure(node, str(path))
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except _DuplicateKey as exc:
        raise ConfigError(f"{path}:{exc.line}: duplicate key {exc.key!r} (first written at line {exc.first}); "
                          "each key may appear once per section") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{where}: YAML syntax error: {problem}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at the top level, got {type(data).__name__}")
    return data, (_line_index(node, str(path)) if node is not None else {})


def _blame_override(lines: dict[tuple, str], key: tuple, where: str) -> None:
    """Problems at or under an overridden key, and at sections it created, are the override's, not the file's."""
    for k in [k for k in lines if k[: len(key)] == key]:
        del lines[k]
    lines[key] = where
    for n in range(1, len(key)):
        lines.setdefault(key[:n], where)


def load_config(
    path: str | os.PathLike = DEFAULT_CONFIG,
    profile: str | None = None,
    overrides: Sequence[str] = (),
) -> Config:
    """Load, merge profile and ``--set`` overrides, and validate ``experiments.yaml``."""
    path = Path(path)
    raw, lines = _read_yaml(path)
    if profile is not None:
        profiles = raw.get("profiles") or {}
        if profile not in profiles:
            names = ", ".join(sorted(profiles)) or "none defined"
            raise ConfigError(f"{path}: profiles.{profile}: no such profile (available: {names})")
        if not isinstance(profiles[profile], dict):
            raise ConfigError(f"{path}: profiles.{profile}: must be a mapping of overrides")
        raw = deep_merge(raw, profiles[profile])
        prefix = ("profiles", profile)
        lines = {**lines, **{k[2:]: v for k, v in lines.items() if k[:2] == prefix}}
    keys = []
    for text in overrides:
        key, value = parse_override(text)
        set_path(raw, key, value, where=f"--set {text}")
        _blame_override(lines, tuple(key.split(".")), f"--set {text}")
        keys.append((key, text))
    cfg = validate(raw, str(path), lines, path.resolve().parent, profile)
    _check_plan_overrides(cfg, keys)
    return cfg


def _check_plan_overrides(cfg: Config, keys: Sequence[tuple[str, str]]) -> None:
    """A ``--set grid.<field>`` that the stages override is refused (no stage uses it) or warned (some ignore
    it), in one line saying what decides the cells: never silently dropped."""
    for key, text in keys:
        for field in _grid_fields(key, text):
            message, refused = override_problem(cfg.stages, field, text)
            if refused:
                raise ConfigError(urls.redact(message))
            if message:
                log.warning("%s", urls.redact(message))


def _grid_fields(key: str, text: str) -> list[str]:
    """The ``grid.<field>`` paths a ``--set`` writes (``grid={arch: [...]}`` writes each of its keys)."""
    if key == "grid":
        value = parse_override(text)[1]
        return [f"grid.{k}" for k in value] if isinstance(value, dict) else []
    return [key] if key.startswith("grid.") else []

