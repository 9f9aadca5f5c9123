"""Every path and URL of a config, resolved once, and the checks made before anything is written there.

``Paths.of(cfg, base)`` expands ``${VAR}`` and ``~`` and resolves relative paths against the config file's
folder (not the working directory). ``check_paths`` looks at every folder and database file a command
would write, before any of them is created, and names the setting of the first that cannot be written.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .. import urls
from ..errors import BronchoError

if TYPE_CHECKING:
    from .schema import Config


@dataclass(frozen=True)
class Paths:
    """Every path and URL of a config, resolved once (``${VAR}``, ``~``, relative to the config's folder)."""

    base: Path
    dataset: Path
    cache: Path
    checkpoints: Path
    artifacts: Path
    sweep_logs: Path
    pretrained: Path | str | None  # "imagenet" stays the literal name (models/pretrained.py)
    anatomy: Path | None  # None: procedural
    centreline: Path | None
    speed_settings: Path | None  # None: the shipped settings (bronchocli/speed.py)
    mlflow_uri: str
    storage_url: str

    @classmethod
    def of(cls, cfg: Config, base: Path) -> "Paths":
        def path(p: str | None) -> Path | None:
            if p is None:
                return None
            q = Path(os.path.expandvars(p)).expanduser()
            return q if q.is_absolute() else (base / q).resolve()

        gen = cfg.dataset.generate
        return cls(
            base=base, dataset=path(cfg.dataset.root), cache=path(cfg.data.cache_dir),
            checkpoints=path(cfg.runs.checkpoints), artifacts=path(cfg.runs.artifacts),
            sweep_logs=path(cfg.sweep.logs),
            pretrained=cfg.model.pretrained if cfg.model.pretrained == "imagenet" else path(cfg.model.pretrained),
            anatomy=None if gen.anatomy == "procedural" else path(gen.anatomy), centreline=path(gen.centreline),
            speed_settings=path(cfg.train.speed_settings),
            mlflow_uri=urls.resolve(cfg.runs.uri, base), storage_url=urls.resolve(cfg.storage.url, base),
        )


# -- pre-flight: one line before anything is created -----------------------------------------------------------

def _why_not_writable(folder: Path) -> str | None:
    """Why nothing can be created in the existing folder ``folder`` (None: it can)."""
    try:
        if os.statvfs(folder).f_flag & os.ST_RDONLY:
            return "read-only file system"
    except OSError as exc:
        return exc.strerror or str(exc)
    if not os.access(folder, os.W_OK | os.X_OK):
        return "permission denied"
    return None


def check_output(path: Path, setting: str, kind: str = "folder") -> None:
    """``path`` (a folder, or a ``file`` to create) can be written: BronchoError naming the setting otherwise.

    Creates nothing: the nearest existing ancestor must be a folder this user may write in, on a writable
    file system, and ``path`` itself, if it exists, must be of the right kind (and writable).
    """
    if path.exists():
        if kind == "folder" and not path.is_dir():
            raise BronchoError(f"{setting} {path}: is a file, not a folder; point {setting} at a folder")
        if kind == "file" and path.is_dir():
            raise BronchoError(f"{setting} {path}: is a folder, not a database file; point {setting} at a file")
        target = path if path.is_dir() else path.parent
        why = _why_not_writable(target)
        if why is not None:
            raise BronchoError(f"{setting} {path}: cannot write there ({why}); point {setting} at a writable place")
        return
    nearest = path.parent
    while not nearest.exists() and nearest != nearest.parent:
        nearest = nearest.parent
    if not nearest.is_dir():
        raise BronchoError(f"{setting} {path}: {nearest} is a file, so no {kind} can be created there")
    why = _why_not_writable(nearest)
    if why is not None:
        raise BronchoError(f"{setting} {path}: cannot create it in {nearest} ({why}); point {setting} at a "
                           "writable place")


def check_dataset_root(cfg: Config) -> None:
    """``dataset.root`` is a folder (or missing, to be generated): a file there is one line, before anything runs."""
    root = cfg.paths.dataset
    if root.exists() and not root.is_dir():
        raise BronchoError(f"dataset.root {root}: is a file, not a dataset folder; point dataset.root at the "
                           "folder holding dataset.json (or at a new folder to generate one there)")
    if not root.exists():
        check_output(root, "dataset.root")


def check_paths(cfg: Config, *, storage: bool = False, logs: bool = False) -> None:
    """Every folder and database file a training command writes, checked before any is created (one line each).

    ``storage``: also the SQLite file of ``storage.url`` (sweep, tune); ``logs``: the sweep's worker logs.
    """
    check_dataset_root(cfg)
    outputs = [(cfg.paths.checkpoints, "runs.checkpoints", "folder"), (cfg.paths.cache, "data.cache_dir", "folder")]
    mlflow_db = urls.sqlite_file(cfg.paths.mlflow_uri)
    if mlflow_db is not None:
        outputs += [(mlflow_db, "runs.uri", "file"), (cfg.paths.artifacts, "runs.artifacts", "folder")]
    elif not urls.is_server(cfg.paths.mlflow_uri) and not urls.is_postgres(cfg.paths.mlflow_uri):
        outputs.append((cfg.paths.artifacts, "runs.artifacts", "folder"))
    storage_db = urls.sqlite_file(cfg.paths.storage_url)
    if logs:
        outputs.append((cfg.paths.sweep_logs, "sweep.logs", "folder"))
    if storage_db is not None and storage:
        outputs.append((storage_db, "storage.url", "file"))
    for path, setting, kind in outputs:
        check_output(path, setting, kind)
