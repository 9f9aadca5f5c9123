"""Every path and URL of a config, resolved once, and the checks made before anything is written there.

``Paths.of(cfg, base)`` expands ``${VAR}`` and ``~`` and resolves relative paths against the config file's
folder (not the working directory). ``check_paths`` looks at every folder and database file a command
would write, before any of them is created, and names the setting of the first that cannot be written; each
goes through ``pathcheck.check_output``, the one check of a path to write that ``--out`` flags use too.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from .. import pathcheck, urls
from ..errors import BronchoError, ConfigError
from ..pathcheck import check_output

DATASET_JSON = "dataset.json"  # what a generated dataset folder holds once complete (data/naming.py, a higher layer)

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
        """Every path resolved (``pathcheck``: an undefined ``${VAR}``, a symlink loop or an output root in a
        system folder is a ConfigError naming the key)."""
        try:
            return cls._of(cfg, base)
        except ConfigError:
            raise
        except BronchoError as exc:
            raise ConfigError(str(exc)) from None

    @classmethod
    def _of(cls, cfg: Config, base: Path) -> "Paths":
        def path(p: str | None, key: str, output: bool = False) -> Path | None:
            return None if p is None else _resolve(p, key, base, output)

        def url(u: str, key: str) -> str:
            resolved = urls.resolve(u, base, key)
            if (db := urls.sqlite_file(resolved)) is not None:
                pathcheck.resolve(db, key)
            return resolved

        gen = cfg.dataset.generate
        return cls(
            base=base, dataset=path(cfg.dataset.root, "dataset.root"),
            cache=path(cfg.data.cache_dir, "data.cache_dir", output=True),
            checkpoints=path(cfg.runs.checkpoints, "runs.checkpoints", output=True),
            artifacts=path(cfg.runs.artifacts, "runs.artifacts", output=True),
            sweep_logs=path(cfg.sweep.logs, "sweep.logs", output=True),
            pretrained=cfg.model.pretrained if cfg.model.pretrained in ("imagenet", "imagenet-if-present")
            else path(cfg.model.pretrained, "model.pretrained"),  # names of weights, not files (models/pretrained.py)
            anatomy=None if gen.anatomy == "procedural" else path(gen.anatomy, "dataset.generate.anatomy"),
            centreline=path(gen.centreline, "dataset.generate.centreline"),
            speed_settings=path(cfg.train.speed_settings, "train.speed_settings"),
            mlflow_uri=url(cfg.runs.uri, "runs.uri"), storage_url=url(cfg.storage.url, "storage.url"),
        )


def _resolve(p: str, key: str, base: Path, output: bool) -> Path:
    q = Path(pathcheck.expand(p, key)).expanduser()
    real = pathcheck.resolve(q, key, base)  # a symlink loop is one line here, whatever reads it later
    if output:
        pathcheck.check_writable_root(real, key, configured=p)
    return q if q.is_absolute() else real


def output_folder(cfg: Config, value: str, key: str) -> Path:
    """A folder setting outside the core sections (a launcher's log folder, ``sweep.launchers.<name>.logs``)
    resolved as ``cfg.paths`` resolves its own: ``${VAR}``, ``~``, relative to the config's folder, never a system
    folder (ConfigError naming ``key``)."""
    try:
        return _resolve(value, key, cfg.paths.base, output=True)
    except ConfigError:
        raise
    except BronchoError as exc:
        raise ConfigError(str(exc)) from None


# -- pre-flight: one line before anything is created -----------------------------------------------------------

def check_dataset_root(cfg: Config) -> None:
    """``dataset.root`` is a folder (or missing, to be generated): a file there is one line, before anything runs;
    a folder the dataset will be generated into passes ``check_output`` (never a system folder)."""
    root = cfg.paths.dataset
    if root.exists() and not root.is_dir():
        raise BronchoError(f"dataset.root {root}: is a file, not a dataset folder; point dataset.root at the "
                           "folder holding dataset.json (or at a new folder to generate one there)")
    if not root.exists() or (cfg.dataset.format == "bronchopose" and not (root / DATASET_JSON).exists()):
        check_output(root, "dataset.root")


Roots = Sequence[tuple[str, Path]]  # (setting name, resolved folder)


def roots(cfg: Config, extra: Roots = ()) -> list[tuple[str, Path]]:
    """The folders the project writes into and cleans up after (setting name, resolved path); ``extra``: those of
    the sections it does not know (a launcher's log folder: ``Launcher.roots``)."""
    return [("runs.checkpoints", cfg.paths.checkpoints), ("runs.artifacts", cfg.paths.artifacts),
            ("data.cache_dir", cfg.paths.cache), ("sweep.logs", cfg.paths.sweep_logs), *extra]


def _real(path: Path) -> Path:
    return Path(os.path.realpath(path))  # symlinks followed, a loop left as is (no error)


def _inside(a: Path, b: Path) -> bool:
    return a == b or b in a.parents


def check_roots(cfg: Config, extra: Roots = ()) -> None:
    """Each root (``roots``) its own folder: none equal to or inside another. One line naming both settings
    otherwise, before anything is written or removed (``sweep gc`` once deleted every folder inside a checkpoints
    root that held the artifacts). System folders, the file system's root and home are refused for every output
    root when the config is read (``pathcheck.check_writable_root``, through ``Paths.of``)."""
    found = [(name, path, _real(path)) for name, path in roots(cfg, extra)]
    for i, (name, path, real) in enumerate(found):
        for other, opath, oreal in found[i + 1:]:
            if _inside(real, oreal) or _inside(oreal, real):
                outer, inner = ((other, opath), (name, path)) if _inside(real, oreal) else ((name, path), (other, opath))
                how = "is the same folder as" if real == oreal else "contains"
                names = ", ".join(n for n, *_ in found[:-1]) + f" and {found[-1][0]}"
                raise BronchoError(f"{outer[0]} {outer[1]}: {how} {inner[0]} {inner[1]}; give {names} each a folder "
                                   "of its own, none inside another")


def check_paths(cfg: Config, *, storage: bool = False, logs: bool = False, extra: Roots = ()) -> None:
    """Every folder and database file a training command writes, checked before any is created (one line each).

    ``storage``: also the SQLite file of ``storage.url`` (sweep, tune); ``logs``: the sweep's worker logs;
    ``extra``: roots of sections it does not know (a launcher's logs: ``Launcher.roots``).
    The roots are checked first (``check_roots``).
    """
    check_roots(cfg, extra)
    check_dataset_root(cfg)
    outputs = [(cfg.paths.checkpoints, "runs.checkpoints", "folder"), (cfg.paths.cache, "data.cache_dir", "folder")]
    mlflow_db = urls.sqlite_file(cfg.paths.mlflow_uri)
    if mlflow_db is not None:
        outputs += [(mlflow_db, "runs.uri", "database file"), (cfg.paths.artifacts, "runs.artifacts", "folder")]
    elif not urls.is_server(cfg.paths.mlflow_uri) and not urls.is_postgres(cfg.paths.mlflow_uri):
        outputs.append((cfg.paths.artifacts, "runs.artifacts", "folder"))
    storage_db = urls.sqlite_file(cfg.paths.storage_url)
    if logs:
        outputs.append((cfg.paths.sweep_logs, "sweep.logs", "folder"))
    if storage_db is not None and storage:
        outputs.append((storage_db, "storage.url", "database file"))
    for path, setting, kind in outputs:
        check_output(path, setting, kind)
