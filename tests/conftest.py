"""Shared fixtures: the repository root and a CLI runner that checks exit codes."""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import pytest
from mounts import tmpfs

REPO = Path(__file__).resolve().parents[1]
# A copy of ../shared/data/airways (CT-derived tree of the Chaste project, BSD-3, licence beside it),
# kept in the repository so a clean checkout anywhere runs the real-anatomy tests.
REAL_TREE = REPO / "tests" / "fixtures" / "airways" / "TestSubject002MajorAirways.vtu"

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture
def one_thread():
    """Tiny inputs: one torch thread (a team of threads on a shared CPU is ten times slower here)."""
    import torch  # lazy: most tests never load torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def real_tree() -> Path:
    assert REAL_TREE.is_file(), f"{REAL_TREE} is missing from the checkout"
    return REAL_TREE


@pytest.fixture
def cli(monkeypatch):
    """Run ``bronchocli.cli.main`` in-process, through the console script's own error and exit-code path.

    Returns (exit code, stdout, stderr). An exception that ``main`` lets through
    (a traceback for a user) fails the test.
    """
    from bronchocli.cli import main

    monkeypatch.setenv("COLUMNS", "200")
    monkeypatch.setenv("NO_COLOR", "1")

    def run(*args: str) -> tuple[int, str, str]:
        out, err = io.StringIO(), io.StringIO()
        code = 0
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main([str(a) for a in args])
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        return code, out.getvalue(), err.getvalue()

    return run


@pytest.fixture
def small_fs(tmp_path):
    """A 1 MB tmpfs mounted at ``tmp_path/small``."""
    with tmpfs(tmp_path / "small", "1m") as mount:
        yield mount


def pytest_collection_modifyitems(config, items):
    """``gpu`` tests run where CUDA exists and are skipped with the reason elsewhere."""
    # The marker, not ``item.keywords``: keywords hold every parent node's name, so a checkout in a folder
    # named ``gpu`` would skip the whole suite.
    if not any(item.get_closest_marker("gpu") for item in items):
        return
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device (run `pytest -m gpu` in a GPU session)")
    for item in items:
        if item.get_closest_marker("gpu"):
            item.add_marker(skip)
