"""Fixtures of the report tests: the golden sweep on a temporary MLflow store (built once per session)."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # report_fakes, shared with benchmarks/bench_report.py

from report_fakes import EXPERIMENT, SWEEP, fabricate_golden, fast_sqlite, new_store, write_config  # noqa: E402
from tinydata import write_tiny_dataset  # noqa: E402


@dataclass(frozen=True)
class Golden:
    client: object
    uri: str
    ids: dict[str, str]  # label -> run id
    config: Path  # the experiments.yaml the sweep was made from (its cell keys are the runs' cell_key)
    cfg: object  # that config, loaded


@pytest.fixture(scope="session")
def golden_store(tmp_path_factory) -> Golden:
    """The golden sweep (built once per test session; do not modify it)."""
    root = tmp_path_factory.mktemp("golden-store")
    fast_sqlite(root.parent)  # every store of this test session
    client, exp_id, uri = new_store(root)
    data = write_tiny_dataset(root / "data", patients=3, trajectories=1, frames=6)
    path, cfg = write_config(root / "experiments.yaml", sweep=SWEEP, uri=uri, experiment=EXPERIMENT, data=data)
    ids = fabricate_golden(client, exp_id, cfg)
    return Golden(client, uri, ids, path, cfg)
