"""runs.processes: a run whose process died mid model logging leaves no logged model PENDING (issue 32.7)."""

from __future__ import annotations

import os
import socket

from mlflow.tracking import MlflowClient

from bronchocli.runs.processes import TAG_HOST, TAG_PID, TAG_PSTART, repair_zombie


def test_repairing_a_dead_run_fails_the_logged_model_it_left_pending(tmp_path):
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.create_experiment("e", artifact_location=(tmp_path / "artifacts").as_uri())
    # a run of a process on this host that is gone (this pid, another start tick: the pid was reused)
    run = client.create_run(exp, tags={TAG_HOST: socket.gethostname(), TAG_PID: str(os.getpid()),
                                       TAG_PSTART: "-1"})
    pending = client.create_logged_model(exp, name="model", source_run_id=run.info.run_id)
    other = client.create_run(exp)
    ready = client.create_logged_model(exp, name="model", source_run_id=other.info.run_id)
    client.finalize_logged_model(ready.model_id, "READY")
    kept = client.create_logged_model(exp, name="model", source_run_id=other.info.run_id)  # another run's: untouched
    assert str(client.get_logged_model(pending.model_id).status).endswith("PENDING")

    assert repair_zombie(client, client.get_run(run.info.run_id), "status --repair")

    assert client.get_run(run.info.run_id).info.status == "FAILED"
    assert str(client.get_logged_model(pending.model_id).status).endswith("FAILED")
    assert str(client.get_logged_model(ready.model_id).status).endswith("READY")
    assert str(client.get_logged_model(kept.model_id).status).endswith("PENDING")
