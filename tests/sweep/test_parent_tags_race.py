"""A sweep's parent run is tagged by every worker as it starts: two writes of the same new tag at once must both
succeed (MLflow's SQL store upserts a tag by reading, then inserting; the loser of that race gets a unique-key
violation). CI once failed on exactly this: three sweeps started together, one died on ``tag_pk``; this test
failed the same way before ``start_parent`` wrote its tags as one batch."""

from __future__ import annotations

import threading

import pytest

from bronchocli.runs.parents import start_parent


@pytest.mark.postgres
def test_workers_starting_together_all_tag_the_shared_parent(fresh_db):
    """Eight processes' worth of ``start_parent`` on one PostgreSQL-stored run at the same moment: none fails,
    and the parent ends up tagged by one of them."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=fresh_db)
    exp = client.create_experiment("race")
    errors: list[BaseException] = []
    for _ in range(3):  # fresh runs: every round races on inserting the same new tags
        run_id = client.create_run(exp).info.run_id
        barrier = threading.Barrier(8)

        def start() -> None:
            try:
                barrier.wait()
                start_parent(MlflowClient(tracking_uri=fresh_db), run_id)
            except BaseException as exc:  # noqa: BLE001 - collected and asserted below
                errors.append(exc)

        threads = [threading.Thread(target=start) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        run = client.get_run(run_id)
        assert run.info.status == "RUNNING"
        assert {"process.host", "process.pid", "process.start"} <= set(run.data.tags)
    assert not errors, errors[0]
