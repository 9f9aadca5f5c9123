"""bronchopose: vision-based bronchoscopy pose estimation research platform."""

import os
from importlib.metadata import PackageNotFoundError, version

os.environ.setdefault("MPLBACKEND", "Agg")  # figures are files: never ask for a display

try:
    __version__ = version("bronchocli")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"
