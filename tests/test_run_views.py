"""What runs show in MLflow: comparable params, headline ratios/skills, source fields, description, parents."""

from __future__ import annotations

import math
import re

import pytest

from bronchocli.config import Config
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.parents import log_plan_params, set_parent_status, study_parent, sweep_parent
from bronchocli.runs.records import run_name, source_name
from bronchocli.runs.views import (
    HEADLINE,
    README_RATIO,
    CURVE_METRICS,
    CURVES_SECTION,
    EVAL_PARAMS,
    HEADLINE_SECTION,
    VIEW_METRICS,
    ACC_RATIO,
    config_value,
    describe,
    eval_params,
    reference_figures,
    headline_view,
    ordered_metrics,
    rounded,
    text_figure,
    run_params,
    saved_view,
    runs_table_url,
)

METRICS = {  # a model and its two image-blind references, per pair and accumulated
    "pair.pos_l2.mean": 0.84, "zero_motion.pair.pos_l2.mean": 1.2, "train_mean.pair.pos_l2.mean": 1.0,
    "pair.rot_l2.mean": 3.0, "zero_motion.pair.rot_l2.mean": 2.0, "train_mean.pair.rot_l2.mean": 4.0,
    "acc.pos_l2.mean": 10.0, "zero_motion.acc.pos_l2.mean": 8.0, "train_mean.acc.pos_l2.mean": 20.0,
    "acc.rot_l2.mean": 30.0, "traj.ate.mean": 5.0, "val_best.loss": 0.1,
}


def test_params_are_the_coordinates_and_the_settings_that_differ():
    cfg = Config(name="t").with_values({"train.lr": 0.0005, "train.threads": 3, "tune.space": {
        "model.dropout": {"type": "float", "low": 0.0, "high": 0.5}}})
    cell = cfg.cell(arch="lstm", rot_loss="ce", population="personalized", seed=2)
    params = run_params(cfg, cell)
    assert {k: params[k] for k in ("arch", "rot_loss", "population", "seed", "pose_frame")} == {
        "arch": "lstm", "rot_loss": "ce", "population": "personalized", "seed": "2", "pose_frame": "world"}
    assert "fold" not in params and "train_trajectories" not in params  # unset coordinates: no param at all
    assert params["train.lr"] == "0.0005"  # changed from the default
    assert "model.dropout" in params  # a tuned path is always a param, even at its default
    assert params["train.threads"] == "3"  # a speed setting, changed: it explains timing differences
    assert params["model.pretrained"] == "None"  # the initialisation is always a param (default: random)
    # how DE/CE were weighed, at its default too: a run without the param is read as one logged before the setting
    # existed (unscaled), so a default-scaled run that left it out was captioned "unscaled" (2026-12-07)
    assert params["train.rot_scale"] == "label_std"
    assert run_params(cfg.with_values({"train.rot_scale": "none"}), cell)["train.rot_scale"] == "none"
    assert not any(k.startswith(("grid.", "runs.", "storage.", "sweep.", "dataset.")) for k in params)
    assert "train.batch_size" not in params  # at its default: the full value is in config.yaml
    fold = cfg.cell(arch="lstm", rot_loss="ce", population="cross-subject", fold="p01", train_trajectories=4)
    assert run_params(cfg, fold)["fold"] == "p01" and run_params(cfg, fold)["train_trajectories"] == "4"


def test_the_evaluation_constants_are_params_read_back_with_the_old_metrics_as_fallback():
    assert eval_params(Config(name="t")) == {"eval.ctf_position": "5.0", "eval.ctf_position_mm": "5.0",
                                             "eval.ctf_angle": "10.0", "eval.rpe_gap": "10"}  # defaults included
    cfg = Config(name="t").with_values({"eval.ctf_angle": 4.0, "eval.rpe_gap": 3})
    assert set(eval_params(cfg)) == set(EVAL_PARAMS) and eval_params(cfg)["eval.rpe_gap"] == "3"
    assert not any(k.startswith("eval.") for k in run_params(cfg, cfg.cell(arch="lstm", rot_loss="ce",
                                                                            population="personalized")))
    new, old = {"eval.rpe_gap": "3"}, {"eval.rpe_gap": 10.0, "eval.ctf_angle": 4.0}  # a run since / before
    assert config_value(new, {}, "eval.rpe_gap") == 3.0
    assert config_value({}, old, "eval.rpe_gap") == 10.0 and config_value({}, old, "eval.ctf_angle") == 4.0
    assert config_value(new, old, "eval.rpe_gap") == 3.0  # the param wins
    assert config_value({}, {}, "eval.rpe_gap") is None
    assert config_value({"eval.rpe_gap": "x"}, {}, "eval.rpe_gap") is None


def test_headline_ratios_and_skills_against_both_references():
    h = reference_figures(METRICS)
    assert list(h)[:3] == [README_RATIO, "skill.pair.pos_l2", "skill.pair.rot_l2"]
    assert h["ratio.train_mean.pair.pos_l2"] == pytest.approx(0.84)  # the README's figure: 0.84 / 1.0
    assert h["ratio.zero_motion.pair.pos_l2"] == pytest.approx(0.7)
    assert not any(k.startswith(("skill.zero_motion.", "skill.train_mean.")) for k in h)  # = 1 - ratio: not twice
    assert h["skill.pair.pos_l2"] == pytest.approx(1 - 0.84 / 1.0)  # vs the better (lower-error) reference
    assert h["skill.pair.rot_l2"] == pytest.approx(1 - 3.0 / 2.0)  # worse than zero motion: negative
    assert h["skill.acc.pos_l2"] == pytest.approx(1 - 10.0 / 8.0)
    assert "skill.acc.rot_l2" not in h  # no reference logged for it: nothing invented
    first, rest = ordered_metrics(METRICS)
    assert list(first)[0] == README_RATIO and "pair.pos_l2.mean" in first and "acc.pos_l2.mean" in first
    assert set(first) | set(rest) == set(METRICS) | set(h) and not set(first) & set(rest)


def test_description_opens_with_the_model_population_and_seed_and_writes_4_significant_digits():
    """Issue 57.4: the first words a reviewer reads are the model's name (with its loss), population and seed,
    never an internal key (the cell's key and the metric key come last); every figure at 4 significant digits."""
    cell = Config(name="t").cell(arch="offsetnet", rot_loss="mse", population="cross-subject", fold="p02", seed=1)
    before = describe(cell, dataset="synthetic-cpu")
    assert before.startswith("**OffsetNet**, cross-subject (test patient p02), seed 1: ")
    assert before.endswith("cell `offsetnet/mse/cross-subject/p02/s1/world`.") and "Test:" not in before
    after = describe(cell, METRICS)
    first, *rest = after.split("\n\n")
    assert first.startswith("**OffsetNet**, cross-subject (test patient p02), seed 1: ")
    assert cell.label not in first and HEADLINE not in first  # the keys: later in the text
    assert cell.label in rest[-1] and HEADLINE in rest[-1]
    assert "**0.8400 ×** the training-mean reference" in first  # the headline: 0.84 / 1.0
    assert "accumulated (whole trajectories, last pose) **0.5000 ×**" in first  # 10 / 20
    assert "position 0.1600" in after and "accumulated position error 10.00 vox" in after
    figures = re.findall(r"(?<![\w.])-?\d+\.\d+", after)
    assert figures and all(len(f.lstrip("-").lstrip("0.").replace(".", "")) == 4 for f in figures), figures


def test_text_figure_keeps_4_significant_digits_and_their_zeros():
    assert [text_figure(v) for v in (0.84, 12.3, 1234.4, 0.012345, -0.5, 1.5e7)] == [
        "0.8400", "12.30", "1234", "0.01235", "-0.5000", "1.500e+07"]
    assert text_figure(math.nan) == "n/a" and text_figure(math.inf) == "inf"


def test_source_name_is_the_command():
    assert source_name(["/venv/bin/bronchopose", "-q", "sweep", "--workers", "2"]) == "bronchopose sweep"
    assert source_name(["/src/bronchocli/cli.py", "train", "-a", "lstm"]) == "bronchopose train"
    assert source_name(["/usr/lib/python3/site-packages/pytest/__main__.py", "x"]) == "__main__.py"
    assert source_name(["train.py"]) == "train.py"


def test_runs_table_url_opens_the_model_training_view_on_the_headline_view():
    assert runs_table_url("http://127.0.0.1:5000/", "3", view=None) == \
        "http://127.0.0.1:5000/#/experiments/3/runs?workflowType=machine_learning"
    assert runs_table_url("http://127.0.0.1:5000/", "3").endswith("&viewStateShareKey=bronchopose-headline")


def test_the_headline_view_is_stored_as_a_saved_view_mlflow_lists_by_name():
    """Issue 36.5: MLflow 3.17's Views menu lists an experiment tag mlflow.sharedViewState.<key> only in its
    saved-view envelope (a string name, a number createdAt, the view's JSON as the string state)."""
    import json

    envelope = json.loads(saved_view(headline_view(), 1_700_000_000_000))
    assert isinstance(envelope["name"], str) and envelope["name"].startswith("Headline")
    assert envelope["createdAt"] == envelope["updatedAt"] == 1_700_000_000_000
    assert json.loads(envelope["state"]) == headline_view()
    assert len(saved_view(headline_view(), 0)) < 20_000  # MLflow's limit on an experiment tag's value


def test_headline_view_sorts_by_the_headline_and_shows_it_as_columns():
    view = headline_view()
    assert view["orderByKey"] == f"metrics.`{HEADLINE}`" and view["orderByAsc"] is True  # a ratio: lower is better
    assert view["selectedColumns"][:2] == [f"metrics.`{ACC_RATIO}`", f"metrics.`{HEADLINE}`"]  # accumulated beside
    assert all(f"metrics.`{m}`" in view["selectedColumns"] for m in VIEW_METRICS)
    assert sorted(VIEW_METRICS)[:2] == [ACC_RATIO, HEADLINE]  # MLflow orders the columns by name: these come first
    assert "tags.run_kind != 'sweep'" in view["searchFilter"]  # parents (nothing trained) are not in the table


def test_headline_view_columns_are_comparable_across_rows_one_row_per_run():
    """No loss column (CE, DE and MSE losses have different scales and rank runs unlike the headline); one row per
    run, not grouped (issue 48.5: MLflow shows a group's mean with every digit and charts groups, not runs)."""
    view = headline_view()
    assert not any("loss" in c for c in view["selectedColumns"]), view["selectedColumns"]
    assert all(m.startswith(("ratio.", "skill.")) for m in VIEW_METRICS)
    assert view["groupBy"] is None and view["useGroupedValuesInCharts"] is False


def test_the_headline_figures_are_logged_to_4_significant_digits_and_the_errors_whole():
    """Issue 48.5: MLflow's runs table shows a metric as logged (no display precision in 3.17)."""
    metrics = {"pair.pos_l2.mean": 1.23456789, "train_mean.pair.pos_l2.mean": 1.5, "zero_motion.pair.pos_l2.mean": 7.0,
               "pair.rot_l2.mean": 0.0123456, "train_mean.pair.rot_l2.mean": 0.03}
    first, _ = ordered_metrics(metrics)
    assert first["pair.pos_l2.mean"] == 1.23456789  # the error: every digit
    assert first[README_RATIO] == 0.823 and first["ratio.zero_motion.pair.pos_l2"] == 0.1764
    assert first["skill.pair.rot_l2"] == 0.5885  # 1 - 0.0123456 / 0.03 = 0.58848
    assert all(len(repr(first[k]).lstrip("0.").replace(".", "")) <= 4 for k in first if k.startswith(("ratio.",
                                                                                                      "skill.")))
    assert reference_figures(metrics)[README_RATIO] == pytest.approx(1.23456789 / 1.5, rel=1e-12)  # computed whole
    assert rounded(-0.0012346) == -0.001235 and rounded(12345.6) == 12350.0 and math.isnan(rounded(math.nan))


def test_headline_view_charts_put_the_training_and_validation_curves_first_without_renaming_a_metric():
    """The view's Chart sections: the curves, then the headline (MLflow appends any other section after them:
    isAccordionReordered); the metric names stay what every reader and old store know (no "/" prefix invented
    for MLflow's grouping). The headline figures are scatter plots, a point per run (a bar's axis starts at 0)."""
    view = headline_view()
    curves, head = view["compareRunSections"]
    assert (curves["name"], head["name"]) == (CURVES_SECTION, HEADLINE_SECTION) and view["isAccordionReordered"]
    cards = view["compareRunCharts"]
    assert list(CURVE_METRICS) == ["train_loss", "val_loss", "val.ratio.pos_l2", "val.mode_gap"]
    lines = [c for c in cards if c["metricSectionId"] == curves["uuid"]]
    assert [c["metricKey"] for c in lines] == list(CURVE_METRICS) and cards[:len(lines)] == lines
    assert all(c["type"] == "LINE" and c["xAxisKey"] == "step" and not c["deleted"] for c in lines)
    assert [c["scaleType"] for c in lines] == ["log", "log", "linear", "linear"]  # losses of different scales
    scatters = cards[len(lines):]
    assert scatters and all(c["type"] == "SCATTER" and c["metricSectionId"] == head["uuid"] for c in scatters)
    assert {c[a]["key"] for c in scatters for a in ("xaxis", "yaxis")} == set(VIEW_METRICS)  # every column drawn
    assert len({c["uuid"] for c in cards}) == len(cards) and not any("/" in m for m in CURVE_METRICS)


def test_a_run_pages_chart_layout_opens_on_the_curves():
    """Issue 48.5: the layout `bronchopose ui` stores for a run's "Model metrics" (MLflow's chartUIState of its run
    page): the curves' section only, in order, and MLflow's own defaults for the rest."""
    from bronchocli.runs.views import run_page_layout

    layout = run_page_layout()
    (section,) = layout["compareRunSections"]
    assert section["name"] == CURVES_SECTION and layout["isAccordionReordered"] is True
    assert [(c["type"], c["metricKey"], c["metricSectionId"]) for c in layout["compareRunCharts"]] == \
        [("LINE", m, section["uuid"]) for m in CURVE_METRICS]
    assert layout["globalLineChartConfig"]["xAxisKey"] == "step" and layout["autoRefreshEnabled"] is True


def test_the_sweep_parent_has_no_csv_import_params_unless_the_dataset_is_one():
    from bronchocli.runs.views import parent_params

    plain = parent_params(Config(name="t"))
    assert "dataset.root" in plain and not any(k.startswith("dataset.csv.") for k in plain)
    csv = parent_params(Config(name="t").with_values({"dataset.format": "csv"}))
    assert any(k.startswith("dataset.csv.") for k in csv)


def test_run_names_are_the_model_name_and_seed_then_the_telling_coordinates():
    cfg = Config(name="t")
    assert run_name(cfg.cell(arch="convlstm", rot_loss="ce", population="personalized")) == \
        "BronchoTrack · s0 · pers · world"
    assert run_name(cfg.cell(arch="lstm", rot_loss="mse", population="cross-subject", fold="p01", seed=3,
                             pose_frame="camera", train_trajectories=5)) == "+LSTM MSE+MSE · s3 · xs-p01 · camera · t5"
    lite = cfg.cell(arch="convlstm", rot_loss="ce", population="personalized", seed=2)
    assert run_name(lite, "efficientnet_lite0", "imagenet:efficientnet_lite0.pth") == \
        "BronchoTrack · Lite0 ImageNet · s2 · pers · world"


def test_parent_run_is_created_once_and_found_again(tmp_path):
    cfg = Config(name="par").with_values({"runs.uri": f"sqlite:///{tmp_path / 'mlflow.db'}",
                                          "runs.artifacts": str(tmp_path / "art")})
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    assert client.get_experiment(exp).tags["mlflow.experimentKind"] == "custom_model_development"
    first = sweep_parent(client, cfg, exp)
    assert sweep_parent(client, cfg, exp) == first  # found by its tags, not made twice
    run = client.get_run(first)
    assert run.data.tags["run_kind"] == "sweep" and run.data.tags["sweep"] == "par"
    # the shared settings, not the config's grid lists (what ran is the plan's: sweep/summary.py)
    assert "splits.train" in run.data.params and not any(k.startswith(("grid.", "stages.")) for k in run.data.params)
    assert log_plan_params(client, first, {"stage.grid.arch": "lstm", "stage.grid.cells": "2"}) == []
    assert log_plan_params(client, first, {"stage.grid.arch": "lstm,conv3d", "stage.grid.cells": "2"}) == [
        "stage.grid.arch"]  # a changed plan: the param keeps what ran first, a tag of that name the latest
    run = client.get_run(first)
    assert run.data.params["stage.grid.arch"] == "lstm" and run.data.tags["stage.grid.arch"] == "lstm,conv3d"
    study = study_parent(client, cfg, exp, "s1", cfg.cell(arch="lstm", rot_loss="mse",
                                                                    population="personalized"))
    assert study != first and client.get_run(study).data.params["arch"] == "lstm"
    set_parent_status(client, first, 130)
    assert client.get_run(first).info.status == "KILLED"
