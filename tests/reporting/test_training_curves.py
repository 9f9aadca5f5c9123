"""fig-training-curves: every validation's ratio to the training mean and mode gap against the pairs seen."""

from __future__ import annotations

from bronchocli.reporting.collect import RunRecord
from bronchocli.reporting.curves import curves, training_curves

TAGS = {"arch": "baseline", "rot_loss": "ce", "population": "personalized", "fold": "", "seed": "0",
        "pose_frame": "camera", "train_trajectories": ""}


def fake_history(points: dict[str, dict[str, list[tuple[int, float]]]]):
    return lambda run_id, key: points.get(run_id, {}).get(key, [])


def test_the_curves_pair_each_validation_with_the_pairs_seen_at_its_step():
    runs = [RunRecord("a", "FINISHED", 0, TAGS, {"ratio.train_mean.pair.pos_l2": 0.9})]
    history = fake_history({"a": {"train.pairs_seen": [(250, 5000.0), (500, 10000.0)],
                                  "val.ratio.pos_l2": [(250, 0.97), (500, 0.93)],
                                  "val.mode_gap": [(250, 1.02), (500, 1.01)]}})
    got = curves(runs, history)
    assert got == {"Baseline MSE+CE · s0 · pers · camera": {"val.ratio.pos_l2": [(5000.0, 0.97), (10000.0, 0.93)],
                                                         "val.mode_gap": [(5000.0, 1.02), (10000.0, 1.01)]}}


def test_the_figure_is_drawn_from_two_validations_and_skipped_for_runs_without_the_metrics(tmp_path):
    runs = [RunRecord("a", "FINISHED", 0, TAGS, {}), RunRecord("old", "FINISHED", 0, {**TAGS, "seed": "1"}, {})]
    history = fake_history({"a": {"train.pairs_seen": [(1, 20.0), (2, 40.0)], "val.ratio.pos_l2": [(1, 1.0), (2, 0.9)]},
                            "old": {"train.pairs_seen": [(1, 20.0)], "val_loss": [(1, 1.0)]}})
    files = training_curves(runs, history, tmp_path, [])
    assert sorted(p.name for p in files) == ["fig-training-curves.csv", "fig-training-curves.pdf",
                                             "fig-training-curves.png"]
    assert all(p.stat().st_size > 1000 for p in files if p.suffix != ".csv")
    assert training_curves(runs[1:], history, tmp_path / "none", []) == []


def test_the_csv_holds_each_validation_of_the_kept_runs_with_the_loss_logged_at_its_step(tmp_path):
    runs = [RunRecord("a", "FINISHED", 0, TAGS, {}), RunRecord("old", "FINISHED", 0, {**TAGS, "seed": "1"}, {})]
    history = fake_history({"a": {"train.pairs_seen": [(250, 5000.0), (500, 10000.0)],
                                  "val.ratio.pos_l2": [(250, 0.97), (500, 0.93)],
                                  "val.mode_gap": [(500, 1.01)],
                                  "train_loss": [(100, 2.0), (250, 1.5), (500, 1.25)]},
                            "old": {"train.pairs_seen": [(1, 20.0)], "val.ratio.pos_l2": [(1, 1.0)]}})
    files = training_curves(runs, history, tmp_path, [])
    csv = next(p for p in files if p.suffix == ".csv").read_text().splitlines()
    assert csv == ["run,step,train.pairs_seen,val.ratio.pos_l2,val.mode_gap,train_loss",
                   "Baseline MSE+CE · s0 · pers · camera,250,5000,0.97,,1.5",
                   "Baseline MSE+CE · s0 · pers · camera,500,10000,0.93,1.01,1.25"]
