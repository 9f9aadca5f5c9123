"""Shared fixtures: the repository root and a CLI runner that checks exit codes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# A copy of ../shared/data/airways (CT-derived tree of the Chaste project, BSD-3, licence beside it),
# kept in the repository so a clean checkout anywhere runs the real-anatomy tests.
REAL_TREE = REPO / "tests" / "fixtures" / "airways" / "TestSubject002MajorAirways.vtu"

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def real_tree() -> Path:
    assert REAL_TREE.is_file(), f"{REAL_TREE} is missing from the checkout"
    return REAL_TREE


@pytest.fixture
def cli():
    """Run the CLI in-process (like the console script) and return (exit code, stdout, stderr)."""
    from typer.testing import CliRunner

    from bronchocli.cli import app
    from bronchocli.errors import BronchoError

    def run(*args: str) -> tuple[int, str, str]:
        result = CliRunner().invoke(app, list(args))
        if isinstance(result.exception, BronchoError):
            return 2, result.stdout, str(result.exception)
        if result.exception is not None and not isinstance(result.exception, SystemExit):
            raise result.exception
        return result.exit_code, result.stdout, result.stderr

    return run
