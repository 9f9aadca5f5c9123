"""MLflow run records: the printed tracking URI redacted, config flattening, a cell's tags (runs.records, runs.client)."""

from __future__ import annotations

from bronchocli.cells import FIELDS, Cell
from bronchocli.config import Config
from bronchocli.runs.client import redacted_uri
from bronchocli.runs.records import CELL_TAGS, cell_tags, flatten


def test_the_printed_tracking_uri_hides_the_password():
    cfg = Config(name="t", runs={"uri": "postgresql+psycopg://bp:s3cret@db.example:5432/mlflow"})
    assert redacted_uri(cfg) == "postgresql+psycopg://bp:***@db.example:5432/mlflow"
    assert redacted_uri(Config(name="t", runs={"uri": "http://host:5000"})) == "http://host:5000"


def test_flatten_and_cell_tags():
    cfg = Config(name="t")
    flat = flatten(cfg.dump())
    assert flat["train.lr"] == "0.001" and flat["grid.arch"].startswith("['baseline'")
    cell = cfg.cell(arch="lstm", rot_loss="ce", population="cross-subject", fold="p01", seed=3, pose_frame="camera")
    tags = cell_tags(cfg, cell)
    assert (tags["arch"], tags["fold"], tags["seed"], tags["pose_frame"]) == ("lstm", "p01", "3", "camera")
    # an unset coordinate (and an unset profile) is no tag at all, never an empty string
    assert "train_trajectories" not in tags and "profile" not in tags and all(v != "" for v in tags.values())
    assert set(FIELDS) - {"train_trajectories"} <= set(tags) and CELL_TAGS == FIELDS
    assert tags["cell_key"] == cell.key and tags["run_kind"] == "cell" and tags["hparams_source"] == "config"
    assert tags["mlflow.runName"] == "+LSTM MSE+CE · s3 · xs-p01 · camera"
    assert Cell.from_tags(tags) == cell  # the run's tags give its cell back, key included
    tuned = cfg.with_values({"tune.applied": "optuna:s#4"})
    assert cell_tags(tuned, cell)["hparams_source"] == "optuna:s#4"
    sized = cfg.cell(arch="lstm", rot_loss="ce", population="personalized", train_trajectories=4)
    assert cell_tags(cfg, sized)["train_trajectories"] == "4"
    assert Cell.from_tags(cell_tags(cfg, sized)) == sized
