"""What on disk is provably this project's own checkpoint, and the one way to delete it.

Every delete of a checkpoint (``sweep gc``, a finished or pruned run, a sweep worker's takeover or last
failure) goes through :func:`remove_checkpoint`, which asks :func:`owned_checkpoint` first. A folder
``<runs.checkpoints>/<run_id>/`` is ours when

* it holds the marker the run wrote when it saved its first checkpoint (:func:`mark`, naming the run), or
* its ``last.pt`` reads back as a checkpoint of this format whose ``run_id`` is the folder's name (a folder
  written before markers existed). The file's pickle is read with an unpickler that resolves no global at
  all (no torch needed, nothing executed), only the top-level ``format`` and ``run_id`` are looked at.

Only the files a run writes there are ever removed (``last.pt``, ``last.pt.rejected``, the temporary copies of
an interrupted write, the marker); the folder itself goes only once it is empty. Anything else inside (a user's
notes, a folder, a symlink) stays, and so does the folder. A symlink is never followed or removed.
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

from ..io import TEMP_SUFFIX, write_json
from .contract import REJECTED_SUFFIX, RESUME_FILE

log = logging.getLogger(__name__)

MARKER = ".bronchopose-checkpoint.json"  # written by the run beside its first checkpoint: {"run_id", "cell_key"}
CHECKPOINT_FORMAT = 2  # training.checkpoint.FORMAT: the format a readable checkpoint declares
_TEMP = re.compile(rf"^\.{re.escape(RESUME_FILE)}\.\d+-[0-9a-f]{{8}}{re.escape(TEMP_SUFFIX)}$")  # io.temp_name's
OWN_NAMES = (RESUME_FILE, RESUME_FILE + REJECTED_SUFFIX, MARKER)


def is_own_name(name: str) -> bool:
    """A file name a run writes in its checkpoint folder (the only names ever deleted there)."""
    return name in OWN_NAMES or bool(_TEMP.match(name))


def is_waste_name(name: str) -> bool:
    """Never needed: a checkpoint refused on resume, or the temporary copy of an interrupted write."""
    return name == RESUME_FILE + REJECTED_SUFFIX or bool(_TEMP.match(name))


def mark(folder: Path, run_id: str, cell_key: str | None) -> None:
    """Write the marker that proves ``folder`` is run ``run_id``'s checkpoint folder (once)."""
    marker = Path(folder) / MARKER
    if not marker.is_file():
        write_json(marker, {"run_id": run_id, "cell_key": cell_key, "written_by": "bronchopose"})


class _StandIn(dict):
    """What every global a pickle names becomes: inert, accepting whatever the pickle does to it (called, built,
    filled like a dict or a list), so the plain data around it (the top-level dict) reads back."""

    def __init__(self, *args, **kwargs) -> None:  # noqa: ARG002 - arguments ignored on purpose
        super().__init__()

    def __setstate__(self, state) -> None:
        pass

    def append(self, item) -> None:
        pass

    def extend(self, items) -> None:
        pass


class _NoGlobals(pickle.Unpickler):
    """Reads a pickle's plain structure; every global it names becomes :class:`_StandIn` (never imported)."""

    def find_class(self, module: str, name: str):  # noqa: ARG002 - nothing is resolved
        return _StandIn

    def persistent_load(self, pid):  # tensor storages: not needed to read the identity
        return None


def read_identity(path: Path) -> tuple[object, object] | None:
    """``(format, run_id)`` of a torch zip checkpoint, read without torch and without running its pickle; None
    when the file is not one."""
    try:
        with zipfile.ZipFile(path) as zf:
            name = next((n for n in zf.namelist() if n.endswith("/data.pkl") and n.count("/") == 1), None)
            if name is None or zf.getinfo(name).file_size > 64 << 20:
                return None
            with zf.open(name) as fh:
                state = _NoGlobals(fh).load()
    except Exception:  # noqa: BLE001 - not a zip, truncated, not a pickle: not provably a checkpoint
        return None
    return (state.get("format"), state.get("run_id")) if isinstance(state, dict) else None


@dataclass(frozen=True)
class Owned:
    """A checkpoint folder proven ours: the files a run wrote there, and what else it holds (kept)."""

    folder: Path
    proof: str  # "marker" or "checkpoint read back"
    files: tuple[Path, ...]
    foreign: tuple[Path, ...]


def _marker_run(folder: Path) -> str | None:
    marker = folder / MARKER
    if marker.is_symlink() or not marker.is_file():
        return None
    try:
        data = json.loads(marker.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data.get("run_id") if isinstance(data, dict) else None


def owned_checkpoint(folder: Path) -> Owned | None:
    """``folder`` as a checkpoint folder this project wrote, or None when that cannot be proven.

    The one test every deleting caller uses (see the module doc for what counts as proof).
    """
    folder = Path(folder)
    if folder.is_symlink() or not folder.is_dir():
        return None
    if _marker_run(folder) == folder.name:
        proof = "marker"
    else:
        last = folder / RESUME_FILE
        if last.is_symlink() or not last.is_file() or read_identity(last) != (CHECKPOINT_FORMAT, folder.name):
            return None
        proof = "checkpoint read back"
    try:
        entries = sorted(folder.iterdir())
    except OSError:
        return None
    own = tuple(p for p in entries if is_own_name(p.name) and not p.is_symlink() and p.is_file())
    return Owned(folder, proof, own, tuple(p for p in entries if p not in own))


def _size(path: Path) -> int:
    try:
        return path.lstat().st_size
    except OSError:
        return 0


def remove_checkpoint(folder: Path, why: str, *, only_waste: bool = False) -> int:
    """Delete the files a run wrote in ``folder`` (``only_waste``: just the never-needed ones), then the folder if
    nothing else is left; returns the bytes freed. A folder not provably ours is left untouched (0)."""
    owned = owned_checkpoint(folder)
    if owned is None:
        if Path(folder).exists():
            log.warning("left %s alone: not provably a checkpoint folder of this project (%s)", folder, why)
        return 0
    freed = 0
    for path in owned.files:
        if only_waste and not is_waste_name(path.name):
            continue
        size = _size(path)
        try:
            path.unlink()
            freed += size
        except FileNotFoundError:
            pass
    if not only_waste:
        try:
            os.rmdir(owned.folder)
            log.info("removed checkpoint folder %s (%s)", owned.folder, why)
        except OSError:
            log.warning("kept %s: it holds %d file(s) the run did not write (%s)", owned.folder,
                        len(owned.foreign), ", ".join(p.name for p in owned.foreign[:5]))
    return freed


def removable_bytes(folder: Path, *, only_waste: bool = False) -> int:
    """Bytes :func:`remove_checkpoint` would free in ``folder`` (0 when it is not provably ours)."""
    owned = owned_checkpoint(folder)
    if owned is None:
        return 0
    return sum(_size(p) for p in owned.files if not only_waste or is_waste_name(p.name))
