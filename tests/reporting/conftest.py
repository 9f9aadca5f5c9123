"""Fixtures of the report tests: the golden sweep on a temporary MLflow store (built once per session)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # report_fakes, shared with benchmarks/bench_report.py

from report_fakes import fabricate_golden, new_store  # noqa: E402


@pytest.fixture(scope="session")
def golden_store(tmp_path_factory):
    """(client, uri, {label: run_id}) of the golden sweep (built once per test session; do not modify it)."""
    root = tmp_path_factory.mktemp("golden-store")
    client, exp_id, uri = new_store(root)
    ids = fabricate_golden(client, exp_id)
    return client, uri, ids
