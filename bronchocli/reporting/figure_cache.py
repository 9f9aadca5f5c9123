"""Figures are drawn only when their inputs changed: each group of figures (run figures, skill figures, the
learning curve, the dataset figures) is keyed by a hash of what it is drawn from and of the drawing code.

``FigureCache(out, stage)`` reads ``out/.figure-keys.json`` (what the last report drew, with which key, and
the warnings it gave); ``once(name, key, draw)`` returns the files already in ``out`` when the key is
unchanged and they all exist (replaying their warnings), else calls ``draw(stage)``. ``save()`` stages the
new record, published with the figures (a failed report leaves the old record and files as they were).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from ..io import write_json

RECORD = ".figure-keys.json"
# The modules that draw: a change to one of them redraws everything.
_CODE = ("figures.py", "skill_figures.py", "dataset_figures.py", "report.py", "../plots.py", "figure_cache.py")


def digest(*parts: Any) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else json.dumps(p, sort_keys=True, default=str).encode())
        h.update(b"\0")
    return h.hexdigest()[:20]


def code_key() -> str:
    here = Path(__file__).parent
    return digest(*[(here / name).read_bytes() for name in _CODE if (here / name).is_file()])


def files_key(paths: Iterable[Path]) -> str:
    return digest(*[Path(p).read_bytes() for p in sorted(paths)])


class FigureCache:
    def __init__(self, out: Path, stage: Path) -> None:
        self.out, self.stage = Path(out), Path(stage)
        try:
            self.record: dict[str, Any] = json.loads((self.out / RECORD).read_text())
        except (OSError, ValueError):
            self.record = {}
        self.code = code_key()
        self.reused: list[str] = []

    def once(self, name: str, key: str, warnings: list[str], draw: Callable[[], list[Path]]) -> list[Path]:
        key = digest(key, self.code)
        old = self.record.get(name)
        if old and old.get("key") == key and all((self.out / f).is_file() for f in old["files"]):
            warnings.extend(old.get("warnings", []))
            self.reused.append(name)
            return [self.out / f for f in old["files"]]
        before = len(warnings)
        files = draw()
        self.record[name] = {"key": key, "files": [str(Path(f).relative_to(self.stage)) for f in files],
                             "warnings": warnings[before:]}
        return files

    def save(self) -> Path:
        return write_json(self.stage / RECORD, self.record)
