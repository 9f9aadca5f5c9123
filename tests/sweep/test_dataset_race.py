"""Two runs logging the same dataset input at once through an `mlflow server` on PostgreSQL (issue 37.1).

MLflow's store reads whether the dataset row exists, then inserts it: two requests at once both insert, and the
second gets ``UniqueViolation "dataset_pk"`` (a 400 from the server). The race is made certain here, not left to
chance: a transaction of the test holds the ``datasets`` table in EXCLUSIVE mode (reads go on, inserts wait), so
both requests have found no row and wait on their insert; then it lets them go. A plain MlflowClient fails one of
the two; the platform's client (runs.client.BusyRetryClient, every MLflow call of a run) retries the lost race
and both succeed, with one dataset row between them.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest
from slurm_cluster import start_mlflow_server, stop_mlflow_server

LOG_INPUTS = """
import sys
from mlflow.entities import Dataset, DatasetInput, InputTag
from mlflow.tracking import MlflowClient
from bronchocli.runs.client import BusyRetryClient

url, run_id, digest, mode = sys.argv[1:5]
client = MlflowClient(tracking_uri=url)
if mode == "platform":
    client = BusyRetryClient(client, 30.0, url)
ds = Dataset(name="tiny:train", digest=digest, source_type="local", source='{"uri": "file:///data/tiny"}')
client.log_inputs(run_id, datasets=[DatasetInput(ds, [InputTag("mlflow.data.context", "train")])])
print("logged")
"""


@pytest.fixture
def server(fresh_db, tmp_path):
    backend = fresh_db.replace("postgresql://", "postgresql+psycopg://", 1)
    srv = start_mlflow_server(backend, tmp_path / "artifacts", sys.executable)
    try:
        yield srv, fresh_db
    finally:
        stop_mlflow_server(srv)


def race(url: str, db: str, runs: list[str], digest: str, mode: str) -> list[subprocess.CompletedProcess]:
    """Both runs log the same new dataset while the test holds the table; both wait on their insert; go."""
    import psycopg

    name = db.rsplit("/", 1)[1]
    with psycopg.connect(db) as hold, psycopg.connect(db, autocommit=True) as watch:
        hold.execute("LOCK TABLE datasets IN EXCLUSIVE MODE")  # SELECT goes on, INSERT waits
        procs = [subprocess.Popen([sys.executable, "-c", LOG_INPUTS, url, run_id, digest, mode],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for run_id in runs]
        end = time.monotonic() + 120
        while True:  # both requests have read "no such dataset" and wait to insert it
            waiting = watch.execute(
                "SELECT count(*) FROM pg_stat_activity WHERE datname = %s AND wait_event_type = 'Lock' "
                "AND query ILIKE %s", (name, "%INSERT INTO datasets%")).fetchone()[0]
            if waiting == 2:
                break
            exited = [p for p in procs if p.poll() is not None]
            assert not exited and time.monotonic() < end, [p.communicate()[0] for p in exited]
            time.sleep(0.05)
        hold.rollback()  # the lock goes: one insert wins, the other meets its row
    return [subprocess.CompletedProcess(p.args, p.wait(timeout=120), p.stdout.read()) for p in procs]


@pytest.mark.slow  # ~90 s on 2 cores: MLflow's first migration of the server's fresh database is most of it
@pytest.mark.postgres
def test_a_lost_race_on_the_dataset_row_is_retried_and_both_runs_log_their_input(server):
    from mlflow.tracking import MlflowClient

    srv, db = server
    client = MlflowClient(tracking_uri=srv.url)
    exp = client.create_experiment("race")

    raw = race(srv.url, db, [client.create_run(exp).info.run_id for _ in range(2)], "d1", "raw")
    assert sorted(p.returncode == 0 for p in raw) == [False, True], [p.stdout for p in raw]  # the race is real
    lost = next(p.stdout for p in raw if p.returncode != 0)
    assert "UniqueViolation" in lost and "dataset_pk" in lost, lost

    runs = [client.create_run(exp).info.run_id for _ in range(2)]
    ours = race(srv.url, db, runs, "d2", "platform")
    assert [p.returncode for p in ours] == [0, 0], [p.stdout for p in ours]
    assert all("Traceback" not in p.stdout for p in ours)
    for run_id in runs:  # each run has the dataset as its input
        (inp,) = client.get_run(run_id).inputs.dataset_inputs
        assert (inp.dataset.name, inp.dataset.digest) == ("tiny:train", "d2")
    import psycopg

    with psycopg.connect(db) as conn:  # one row of the dataset between the two runs
        rows = conn.execute("SELECT count(*) FROM datasets WHERE digest = 'd2'").fetchone()[0]
    assert rows == 1, json.dumps(rows)
