"""What the API's arguments are, for a caller that builds its own interface over it (the command line): the
default config file, the named choices of a cell (architectures, rotation losses, populations, pose frames; read
from the registry), the cell's fields, the bounds of the numeric arguments, and the error the API raises for a
bad argument (one line; the command line prints it and exits 2), and the options the installed launchers take
(``launcher_parameters``: the one call here that loads more, the launchers). Light: no torch, MLflow or Optuna."""

from __future__ import annotations

from typing import Any

from ..cells import FIELDS, Arch, Population, PoseFrame, RotLoss
from ..config import DEFAULT_CONFIG
from ..config.arguments import RULES
from ..errors import BronchoError, ConfigError

__all__ = ["DEFAULT_CONFIG", "FIELDS", "RULES", "Arch", "BronchoError", "ConfigError", "Population", "PoseFrame",
           "RotLoss", "launcher_parameters"]


def launcher_parameters(generic_only: bool = False) -> dict[str, Any]:
    """The options the installed launchers take, as ``api.sweep``/``api.tune`` keywords: name -> its ``Parameter``
    (``type``, ``help``, ``default``, ``low``/``high``, ``choices``, ``short``), the generic ones (``workers``,
    ``gpus``, ``per_gpu``) first and once, then each launcher's own (``<launcher>_<option>``); a launcher whose code
    does not load is left out (it is reported when named). ``generic_only``: the generic ones alone."""
    from ..sweep.launchers import parameters  # lazy: the launchers (and what they import) load only when asked

    return parameters(generic_only)
