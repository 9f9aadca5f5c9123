"""MLflow conventions: URL redaction, flattening, tags."""

from __future__ import annotations

from bronchocli import tracking
from bronchocli.config import Config, make_cell


def test_passwords_are_redacted_from_urls():
    assert tracking.redact_url("postgresql+psycopg://bp:s3cret@db.example:5432/sweeps") == (
        "postgresql+psycopg://bp:***@db.example:5432/sweeps")
    assert tracking.redact_url("sqlite:////tmp/x.db") == "sqlite:////tmp/x.db"
    assert tracking.redact_url("http://host:5000") == "http://host:5000"


def test_flatten_and_cell_tags():
    cfg = Config(name="t")
    flat = tracking.flatten(cfg.dump())
    assert flat["train.lr"] == "0.0001" and flat["grid.arch"].startswith("['baseline'")
    cell = make_cell(cfg, "lstm", "ce", "cross-subject", "p01", 3, "camera")
    tags = tracking.cell_tags(cfg, cell)
    assert (tags["arch"], tags["fold"], tags["seed"], tags["pose_frame"]) == ("lstm", "p01", "3", "camera")
    assert tags["cell_key"] == cell.key and tags["run_kind"] == "cell" and tags["hparams_source"] == "config"
    tuned = cfg.with_values({"tune.applied": "optuna:s#4"})
    assert tracking.cell_tags(tuned, cell)["hparams_source"] == "optuna:s#4"
