"""A zero-work cell runner for bench_sweep.py: creates and finishes an MLflow run, nothing else.

Named by ``bronchopose sweep --runner sweep_noop:noop_runner``, with this folder on PYTHONPATH, so the
sweep's spawned workers run it instead of training.
"""

from __future__ import annotations

import time

from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.contract import RunResult
from bronchocli.runs.records import cell_tags


def noop_runner(cfg, cell, *, extra_tags=None, progress=True, run_id_callback=None, **_):
    t0 = time.perf_counter()
    client = client_for(cfg)
    run_id = client.create_run(experiment_id(client, cfg),
                               tags=cell_tags(cfg, cell, **(extra_tags or {}))).info.run_id
    if run_id_callback:
        run_id_callback(run_id)
    client.set_terminated(run_id, "FINISHED")
    return RunResult(run_id, "FINISHED", duration_s=time.perf_counter() - t0)
