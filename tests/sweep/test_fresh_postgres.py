"""Several `bronchopose sweep` processes starting together on a fresh PostgreSQL database (MLflow store and claims).

MLflow creates its tables when it first opens a store; machines that start at
once must not race on that migration (runs.client.client_for serialises it with a
database advisory lock).
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import yaml
from sweep_fakes import FAKE, HERE, runs_by_cell
from tinydata import write_tiny_dataset

from bronchocli.config import load_config
from bronchocli.sweep import SweepStore


# ~40 s (MLflow's first migration of a PostgreSQL database is most of it): in CI, the acceptance test
@pytest.mark.postgres
def test_three_sweeps_starting_together_on_a_fresh_database_all_succeed(tmp_path, fake_dir, fresh_db):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    data = {
        "name": "fresh",
        "runs": {"uri": fresh_db, "artifacts": "artifacts"},
        "storage": {"url": fresh_db},
        "dataset": {"root": "data/tiny"},
        "grid": {"arch": ["baseline", "lstm", "conv3d"], "rot_loss": ["mse", "ce"], "population": ["personalized"],
                 "seed": [0]},
        "sweep": {"max_retries": 0, "heartbeat_s": 0.5, "stale_after_s": 30.0, "poll_s": 0.1},
    }
    path = tmp_path / "experiments.yaml"
    path.write_text(yaml.safe_dump(data))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}
    code = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
    procs = [subprocess.Popen([sys.executable, "-c", code, "sweep", "-c", str(path), *FAKE], cwd=tmp_path, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for _ in range(3)]
    outs = [p.communicate(timeout=300)[0] for p in procs]
    logs = "\n".join(p.read_text() for p in (tmp_path / "runs" / "sweep-logs").rglob("*.log"))
    assert [p.returncode for p in procs] == [0, 0, 0], "\n----\n".join(outs) + logs
    assert not any("Traceback" in o for o in outs), "\n----\n".join(outs)
    cfg = load_config(path)
    rows = SweepStore(cfg.paths.storage_url).rows(cfg.name)
    assert len(rows) == 6
    assert runs_by_cell(cfg, "FINISHED") == {r.cell_key: 1 for r in rows}
