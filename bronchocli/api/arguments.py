"""What the API's arguments are, for a caller that builds its own interface over it (the command line): the
default config file, the named choices of a cell (architectures, rotation losses, populations, pose frames; read
from the registry), the cell's fields, the bounds of the numeric arguments, and the error the API raises for a
bad argument (one line; the command line prints it and exits 2). Light: no torch, MLflow or Optuna."""

from __future__ import annotations

from ..cells import FIELDS, Arch, Population, PoseFrame, RotLoss
from ..config import DEFAULT_CONFIG
from ..config.arguments import RULES
from ..errors import BronchoError, ConfigError

__all__ = ["DEFAULT_CONFIG", "FIELDS", "RULES", "Arch", "BronchoError", "ConfigError", "Population", "PoseFrame",
           "RotLoss"]
