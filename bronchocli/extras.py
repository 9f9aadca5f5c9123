"""Optional dependencies (pyproject extras): a missing one is one line naming the extra to install, exit 2.

A GPU box that only trains, sweeps and reports needs none of them:

* ``render``: VTK and scikit-image, for ``data generate`` (rendering, anatomy
  readers) and the dataset figures' centreline;
* ``postgres``: psycopg, for ``postgresql://`` MLflow or sweep storage;
* ``video``: PyAV, for reading video files;
* ``gpu``: nvidia-ml-py (NVML), for GPU utilisation, memory and power in each
  run's system metrics; without it the runs log CPU, memory, disk and network
  only (never an error: ``runs/system.py``).

``require(extra, what)`` checks before the first import (``importlib`` finds
the module without loading it, so the check costs nothing when it is there);
``from_import_error`` turns an ImportError met anyway into the same message.
"""

from __future__ import annotations

import importlib.util

from .errors import BronchoError

# extra -> (modules it provides, the distribution names shown to the user)
EXTRAS: dict[str, tuple[tuple[str, ...], str]] = {
    "render": (("vtkmodules", "skimage"), "vtk, scikit-image"),
    "postgres": (("psycopg",), "psycopg"),
    "video": (("av",), "av (PyAV)"),
    "gpu": (("pynvml",), "nvidia-ml-py"),
}
MODULE_EXTRA = {m.split(".")[0]: extra for extra, (mods, _) in EXTRAS.items() for m in mods} | {"vtk": "render"}


class MissingExtra(BronchoError):
    """An optional dependency is not installed; the message says which extra installs it."""


def message(extra: str, what: str) -> str:
    return (f"{what} needs the optional dependencies {EXTRAS[extra][1]}, which are not installed: "
            f"pip install 'bronchocli[{extra}]' (or -e '.[{extra}]' in a checkout)")


def _present(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent package missing, or a module blocked in sys.modules
        return False


def missing(extra: str) -> list[str]:
    """The modules of ``extra`` that cannot be imported here."""
    return [m for m in EXTRAS[extra][0] if not _present(m)]


def require(extra: str, what: str, modules: tuple[str, ...] | None = None) -> None:
    """MissingExtra (one line, exit 2) unless the modules of ``extra`` (or just ``modules`` of it) are installed."""
    if any(not _present(m) for m in (modules or EXTRAS[extra][0])):
        raise MissingExtra(message(extra, what))


def from_import_error(exc: ImportError, what: str) -> MissingExtra | None:
    """The one-line error for an ImportError of an optional module; None for any other module."""
    name = (getattr(exc, "name", None) or "").split(".")[0]
    extra = MODULE_EXTRA.get(name)
    return MissingExtra(message(extra, what)) if extra else None
