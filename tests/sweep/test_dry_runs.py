"""Dry runs never act (issue 32, item 3): `sweep plan` with each of its options, `sweep gc --dry-run` and `sweep
cancel --dry-run` leave the claims table, the
MLflow store and every folder byte for byte as they were, and calls no Slurm command that changes anything
(fake `sbatch`, `scancel`, `scontrol` and `squeue` on PATH record each call; `squeue` only reads)."""

from __future__ import annotations

import hashlib

import optuna
import pytest

from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.contract import resume_file
from bronchocli.runs.ownership import mark
from bronchocli.runs.records import cell_tags
from bronchocli.sweep import SweepStore, prepare
from bronchocli.sweep.tuning import studies
from bronchocli.sweep.launchers.slurm import job_comment

DRY_RUNS = [  # (the old `sweep --dry-run` with --launcher slurm, --detach, --retry-failed: refused, exit 2)
    ["plan"],
    ["gc", "--dry-run"],
    ["gc", "--dry-run", "--set", "sweep.launcher=slurm"],
    ["cancel", "--dry-run", "--launcher", "slurm"],  # issued a real scancel before
    ["cancel", "--dry-run", "--set", "sweep.launcher=slurm"],
    ["plan", "--set", "sweep.launcher=slurm"],
    ["plan", "--only", "arch=lstm", "--workers", "2", "--gpus", "none"],
    ["plan", "--use-tuned", "s"],
]
ACTING = ("sbatch", "scancel", "scontrol")


def snapshot(root) -> dict[str, str]:
    """Every file under ``root`` with its content's hash. Left out: SQLite's shared-memory index (readers write
    their read marks into it) and an empty write-ahead log (opened by any connection, removed by the last one):
    neither is content of the store."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and not p.name.endswith("-shm")
            and not (p.name.endswith("-wal") and p.stat().st_size == 0) and "fakebin" not in p.parts}


@pytest.fixture
def finished_project(make_config, tmp_path, monkeypatch):
    """A sweep with a FINISHED cell (and a checkpoint gc would remove), a FAILED one, a Slurm job on the queue."""
    cfg = make_config(sweep={"max_retries": 0})
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    base, lstm = plan.cells
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    for cell, status in ((base, "FINISHED"), (lstm, "FAILED")):
        claim = store.claim(cfg.name, [cell.key], "w:1", max_retries=0, stale_after_s=60)
        run_id = client.create_run(exp, tags=cell_tags(cfg, cell)).info.run_id
        client.set_terminated(run_id, status)
        mark(resume_file(cfg, run_id).parent, run_id, cell.key)
        resume_file(cfg, run_id).write_bytes(b"x" * 100)
        if status == "FINISHED":
            store.finish(claim.token, run_id, 1.0)
        else:
            store.fail(claim.token, "boom", run_id)
    store.close()
    storage = studies.storage_for(cfg)
    study = optuna.create_study(study_name="s", storage=storage)  # for --use-tuned
    study.add_trial(optuna.trial.create_trial(params={}, distributions={}, value=1.0))
    storage.engine.dispose()  # the last connection closes: SQLite moves its write-ahead log into the file
    fake = tmp_path / "fakebin"
    fake.mkdir()
    (fake / "queue").write_text(f"812_[1-2]|812|PENDING|{job_comment(cfg, 'grid')}|None\n")
    for name in (*ACTING, "squeue"):
        script = fake / name
        script.write_text(f'#!/bin/sh\necho "{name} $*" >> "{fake}/calls"\n'
                          + (f'cat "{fake}/queue"\n' if name == "squeue" else "echo 999\n"))
        script.chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake}:/usr/bin:/bin")
    return cfg, fake


@pytest.mark.parametrize("flags", DRY_RUNS, ids=[" ".join(f) for f in DRY_RUNS])
def test_a_dry_run_changes_nothing_and_calls_no_slurm_command_that_acts(cli, finished_project, tmp_path, flags):
    cfg, fake = finished_project
    before = snapshot(tmp_path)
    code, out, err = cli("sweep", *flags, "-c", str(tmp_path / "experiments.yaml"))
    assert code == 0, out + err
    calls = (fake / "calls").read_text().splitlines() if (fake / "calls").exists() else []
    assert not [c for c in calls if c.split()[0] in ACTING], calls
    assert snapshot(tmp_path) == before
    if "cancel" in flags:
        assert "would cancel Slurm job(s) 812" in out and "nothing cancelled" in out
    if "gc" in flags:
        assert "would free" in out and "nothing was removed" in out


def test_a_dry_run_with_a_study_that_does_not_exist_creates_no_database(cli, make_config, tmp_path):
    make_config()
    before = snapshot(tmp_path)
    code, out, err = cli("sweep", "plan", "-c", str(tmp_path / "experiments.yaml"), "--use-tuned", "nosuch")
    assert code == 2 and "no Optuna study named 'nosuch'" in err and len(err.strip().splitlines()) == 1, out + err
    assert snapshot(tmp_path) == before and not (tmp_path / "sweep.db").exists()
