"""Offscreen VTK rendering of bronchoscopy frames: lumen surface, camera, headlight, realism.

Only the dataset generator imports this package (training never needs VTK).
``camera`` is pure NumPy (intrinsics, projection); ``surface`` prepares the
lumen mesh (normals, mucosa colours, spatial blocks); ``scene`` holds the
``FrameRenderer`` that turns a camera pose into an ``H x W x 3`` uint8 frame.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def configure_environment() -> None:
    """Point VTK at EGL (headless) and Mesa's shader cache at a writable local folder.

    Must run before ``vtk`` is first imported in the process; every VTK-using
    module of this package calls it at import time.
    """
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    cache = Path(tempfile.gettempdir()) / f"bronchopose-mesa-{os.getuid() if hasattr(os, 'getuid') else 0}"
    os.environ.setdefault("MESA_SHADER_CACHE_DIR", str(cache))
