"""Tracking and sweep storage in one database: MLflow and Optuna both keep an ``alembic_version`` table, so
Optuna's tables go to a schema of their own (PostgreSQL) or a sibling file (SQLite); the claims table has no
migration bookkeeping and shares the database as is."""

from __future__ import annotations

import optuna
import pytest
from sqlalchemy import create_engine, inspect
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli.config import load_config
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import search_runs
from bronchocli.sweep.tuning import studies, trial as tuning

TARGET = ["-a", "baseline", "-l", "mse", "-P", "personalized", "-q"]
SPACE = """\
tune:
  startup_trials: 1
  warmup_validations: 0
  space:
    train.lr: {type: float, low: 1.0e-5, high: 1.0e-3, log: true}
"""


@pytest.fixture
def project(tmp_path):
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=6, image_size=32)
    write_config(tmp_path, steps=2, val_every=2, extra=SPACE)
    return tmp_path


def _tune_twice_in_one_database(cli, project, url: str) -> None:
    sets = ["--set", f"runs.uri={url}", "--set", f"storage.url={url}"]
    code, out, err = cli("tune", "-c", str(project / "experiments.yaml"), *TARGET, "-n", "2", *sets)
    assert code == 0, out + err
    cfg = load_config(project / "experiments.yaml", overrides=[s for s in sets if s != "--set"])
    study = optuna.load_study(study_name=tuning.study_name(cfg, cfg.cell(arch="baseline", rot_loss="mse",
                                                                          population="personalized")),
                              storage=studies.storage_for(cfg))
    assert studies.finished(study) == 2
    client = client_for(cfg)  # MLflow still opens its store: its migration bookkeeping is intact
    runs = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "trial"})
    assert len(runs) == 2 and {r.info.status for r in runs} <= {"FINISHED", "KILLED"}  # KILLED: pruned
    # a second tune on the same database continues the study (both libraries reopen their tables)
    code, out, err = cli("tune", "-c", str(project / "experiments.yaml"), *TARGET, "-n", "2", *sets)
    assert code == 0, out + err


def test_tune_with_tracking_and_storage_on_one_sqlite_file(cli, project):
    _tune_twice_in_one_database(cli, project, "sqlite:///runs/one.db")
    names = inspect(create_engine(f"sqlite:///{project / 'runs' / 'one.db'}")).get_table_names()
    assert "experiments" in names and "studies" not in names  # MLflow's file; Optuna's tables beside it
    assert studies.optuna_url(load_config(project / "experiments.yaml", overrides=[
        "runs.uri=sqlite:///runs/one.db", "storage.url=sqlite:///runs/one.db"])).endswith("one.optuna.db")


def test_tune_with_tracking_and_storage_on_one_postgresql_database(cli, project, fresh_db):
    _tune_twice_in_one_database(cli, project, fresh_db)
    engine = create_engine(fresh_db.replace("postgresql://", "postgresql+psycopg://"))
    try:
        insp = inspect(engine)
        assert "experiments" in insp.get_table_names() and "studies" not in insp.get_table_names()
        assert "studies" in insp.get_table_names(schema=studies.OPTUNA_SCHEMA)
    finally:
        engine.dispose()


def test_separate_databases_keep_optuna_where_it_was(make_config):
    cfg = make_config()  # tracking sqlite:///mlflow.db, storage sqlite:///sweep.db
    assert studies.optuna_url(cfg) == cfg.paths.storage_url
