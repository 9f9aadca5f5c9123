"""bronchocli.api's work half: train and report as calls with typed results, the same work as the commands."""

from __future__ import annotations

import re

import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli import api, runkeys
from bronchocli.config import load_config
from bronchocli.config.arguments import ArgumentError
from bronchocli.errors import BronchoError
from bronchocli.runs.client import client_for

ONE_CELL = ["grid.arch=[baseline]", "grid.rot_loss=[mse]", "grid.population=[personalized]"]


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("api-project")
    write_tiny_dataset(root / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    return write_config(root)


@pytest.fixture(scope="module")
def trained(project):
    return api.train(project, arch="baseline", rot_loss="mse", population="personalized", overrides=ONE_CELL)


def test_train_returns_the_run_mlflow_recorded(project, trained):
    assert isinstance(trained, api.TrainResult) and trained.ok and trained.trained
    run = client_for(load_config(project, overrides=ONE_CELL)).get_run(trained.run_id)
    assert run.info.status == "FINISHED" and run.data.tags["cell_key"] == trained.cell.key
    logged = run.data.metrics
    model, mean = logged[runkeys.metric("pos_l2")], logged[runkeys.metric("pos_l2", ref="train_mean")]
    assert trained.errors()["model"] == pytest.approx(model)
    assert trained.headline == pytest.approx(model / mean)
    assert trained.summary().startswith(f"run {trained.run_id} FINISHED in ")


def test_a_second_train_returns_the_finished_run_without_training(project, trained):
    again = api.train(project, arch="baseline", rot_loss="mse", population="personalized", overrides=ONE_CELL)
    assert not again.trained and again.ok and again.run_id == trained.run_id
    assert again.headline == pytest.approx(trained.headline)
    assert "not trained again" in again.summary()


def test_report_returns_its_tables_as_frames_that_match_the_written_markdown(project, trained, tmp_path):
    out = tmp_path / "reports"
    result = api.report(project, table="personalized", evaluation="pair", out=out, figures=False, latency=False,
                        to_parent=False, overrides=ONE_CELL)
    assert isinstance(result, api.ReportResult)
    assert sorted(p.name for p in result.files) == sorted(p.name for p in out.iterdir())
    table = result.table("table3")
    frame = table.frame()
    assert list(frame["Loss"]) == [row.label for row in table.rows]
    baseline = frame[frame["Network"] == "Baseline"].iloc[0]
    # the Markdown file prints the same mean (at the table's decimals) as the frame holds unrounded
    markdown = (out / f"{table.key}.md").read_text()
    line = next(ln for ln in markdown.splitlines() if ln.startswith("| Baseline"))
    shown = line.split("|")[3].strip().split(" ")[0].strip("*")
    decimals = len(shown.partition(".")[2])
    assert abs(float(shown) - baseline["Position L2 (vox)"]) <= 0.5 * 10 ** -decimals
    assert baseline["Position L2 (vox) lo"] < baseline["Position L2 (vox)"] < baseline["Position L2 (vox) hi"]


def test_report_checks_its_arguments_before_reading_any_run(project, tmp_path):
    with pytest.raises(BronchoError, match="--table 'nope': must be one of all, "):
        api.report(project, table="nope", out=tmp_path / "r")
    with pytest.raises(ArgumentError, match=r"^api.report: best=-1: must be an integer >= 0 \(as --best on the "):
        api.report(project, best=-1, out=tmp_path / "r")
    assert not (tmp_path / "r").exists()


def test_a_loaded_config_is_taken_as_is_and_a_profile_beside_it_is_refused(project):
    cfg = load_config(project)
    assert api.config_of(cfg) is cfg
    assert api.config_of(cfg, overrides=["train.steps=7"]).train.steps == 7
    with pytest.raises(BronchoError, match="profile: only with a config file"):
        api.config_of(cfg, profile="paper")


def test_status_shows_the_trained_cell_finished_with_its_run_and_headline(project, trained):
    state = api.status(project, overrides=ONE_CELL)
    (cell,) = state.cells()
    assert (cell.key, cell.state, cell.run_id) == (trained.cell.key, "finished", trained.run_id)
    assert cell.headline == pytest.approx(trained.headline, rel=1e-3)  # logged to 4 significant digits
    # trained by `train`, not by a sweep: the claims table does not know it, MLflow does (status says so)
    assert any("FINISHED in MLflow but not in the claims table" in line for line in state.before)


def test_tune_returns_the_study_optuna_stored_and_study_reads_it_back(project):
    import optuna

    result = api.tune(project, arch="baseline", rot_loss="mse", population="personalized", trials=2,
                      overrides=ONE_CELL)
    assert isinstance(result, api.StudyResult)
    cfg = load_config(project, overrides=ONE_CELL)
    stored = optuna.load_study(study_name=result.study, storage=cfg.paths.storage_url)
    complete = [t for t in stored.trials if t.state == optuna.trial.TrialState.COMPLETE]
    assert result.counts["complete"] == len(complete) and sum(result.counts.values()) == len(stored.trials) >= 2
    if complete:  # a pruned pair of trials leaves no best: then there is none to compare
        assert (result.best_number, result.best_value) == (stored.best_trial.number, stored.best_trial.value)
        assert result.best_params == stored.best_trial.params
    assert api.study(project, result.study, overrides=ONE_CELL) == result


def test_the_documented_notebook_session_runs_a_sweep_and_reads_table3_as_a_dataframe(tmp_path, capsys):
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "api.md").read_text()
    block = re.search(r"<!-- executed by tests/test_api.py -->\n```python\n(.*?)```", text, re.S)
    assert block, "docs/api.md: the tested notebook block is missing"
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    config = write_config(tmp_path)
    grid = "grid: {folds: [p01], seed: [0]}"
    assert grid in config.read_text()
    config.write_text(config.read_text().replace(grid, "grid: {folds: [p01], seed: [0, 1], arch: [baseline], "
                                                      "rot_loss: [mse], population: [personalized]}"))
    namespace = {"CONFIG": str(config), "OUT": str(tmp_path / "reports")}
    exec(compile(block.group(1), "docs/api.md", "exec"), namespace)
    done, table3 = namespace["done"], namespace["table3"]
    cells = done.state.cells()
    assert done.exit_code == 0 and [c.state for c in cells] == ["finished", "finished"]
    runs = client_for(load_config(config)).search_runs(
        [client_for(load_config(config)).get_experiment_by_name("tiny").experiment_id],
        "attributes.status = 'FINISHED' and tags.run_kind = 'cell'")
    assert sorted(c.run_id for c in cells) == sorted(r.info.run_id for r in runs)
    assert list(table3["Network"])[0] == "Baseline" and "Position L2 (vox) hi" in table3.columns
    assert "x the training mean" in capsys.readouterr().out


@pytest.mark.parametrize("call, kwargs, line", [
    (api.sweep, {"workers": "2"}, "api.sweep: workers='2': must be an integer from 1 to 1024 (as --workers on the "
                                  "command line)"),
    (api.sweep, {"workers": 0}, "api.sweep: workers=0: must be an integer from 1 to 1024 (as --workers"),
    (api.sweep, {"only": "arch=lstm"}, "api.sweep: only='arch=lstm': must be a list of strings (not one string) "
                                       "(as --only"),
    (api.train, {"arch": "baseline", "rot_loss": "mse", "population": "personalized", "seed": 1.5},
     "api.train: seed=1.5: must be an integer (as --seed on the command line)"),
    (api.train, {"arch": "baseline", "rot_loss": "mse", "population": "personalized", "seed": True},
     "api.train: seed=True: must be an integer"),
    (api.train, {"arch": "baseline", "rot_loss": "mse", "population": "personalized",
                 "overrides": "train.steps=3"}, "api.train: overrides='train.steps=3': must be a list of strings"),
    (api.tune, {"arch": "baseline", "rot_loss": "mse", "population": "personalized", "trials": "2"},
     "api.tune: trials='2': must be an integer >= 1 (as --trials"),
    (api.tune, {"arch": "baseline", "rot_loss": "mse", "population": "personalized", "timeout": -5},
     "api.tune: timeout=-5: must be a number >= 0.001 (as --timeout"),
    (api.tune, {"arch": "baseline", "rot_loss": "mse", "population": "personalized", "timeout": float("nan")},
     "api.tune: timeout=nan: must be a number >= 0.001"),
    (api.status, {"sweep": 3}, "api.status: sweep=3: must be a string (as --sweep"),
    (api.config_of, {"overrides": "a=1"}, "api.config_of: overrides='a=1': must be a list of strings"),
    (api.train, {"arch": "baseline", "rot_loss": "mse"}, "api.train: missing a required argument: 'population'"),
])
def test_the_api_refuses_what_the_command_line_refuses_naming_the_argument_before_any_work(
        tmp_path, call, kwargs, line):
    """Issue 60, item 3: the CLI's own rules (config.arguments) at every public call's boundary, one ArgumentError
    naming the argument; nothing is read or created (the config file does not even exist)."""
    with pytest.raises(ArgumentError) as err:
        call(tmp_path / "experiments.yaml", **kwargs)
    assert str(err.value).startswith(line), str(err.value)
    assert list(tmp_path.iterdir()) == []


def test_the_command_lines_bounds_are_the_apis():
    """One definition: the options' Typer bounds are read from the same rules (a change of one changes both); the
    launchers' options are added when a command parses its flags (``get_params``: ``commands/launcher_flags.py``)."""
    import typer.main
    from typer._click import Context

    from bronchocli.cli import app
    from bronchocli.config.arguments import RULES

    group = typer.main.get_group(app)
    seen = 0
    for path in (["tune"], ["sweep", "run"], ["train"], ["report"]):
        command = group
        for name in path:
            command = command.commands[name]
        for param in command.get_params(Context(command)):
            flag = max(param.opts, key=len)
            rule = next((r for r in RULES.values() if r.flag == flag and r.kind in (int, float)), None)
            if rule is None or rule.low is None:
                continue
            assert (param.min, param.max) == (rule.low, rule.high), (path, flag)
            seen += 1
    assert seen >= 8


@pytest.mark.parametrize("relative, first_pose, line", [
    ([[0.0] * 5] * 3, None, "relative: shape (3, 5): must be [T, 6]"),
    ([[0.0] * 6] * 3, [1, 2], "first_pose: shape (2,): must be [6]"),
    ([[0.0] * 6] * 3, [float("nan")] * 6, "first_pose: not finite"),
    ("0,0,0", None, "relative: must be an array of numbers"),
])
def test_chain_refuses_poses_of_the_wrong_shape_naming_the_argument(relative, first_pose, line):
    class Model:
        pose_frame = "world"

    with pytest.raises(ArgumentError, match="^" + re.escape(f"api.chain: {line}")):
        api.chain(Model(), relative, first_pose)


def test_a_sweep_started_again_by_a_worker_importing_an_unguarded_script_says_what_to_add(
        tmp_path, monkeypatch, capsys):
    """A spawned worker imports the script that started it as ``__mp_main__``: a top-level ``api.sweep`` there is
    one line naming the guard to add and the worker exits 2 (no bootstrapping traceback, no second sweep)."""
    import sys
    import types

    script = types.ModuleType("__mp_main__")
    script.__file__ = str(tmp_path / "my_sweep.py")
    monkeypatch.setitem(sys.modules, "__main__", script)
    with pytest.raises(SystemExit) as stop:
        api.sweep(tmp_path / "experiments.yaml", workers=2)
    assert stop.value.code == 2
    assert capsys.readouterr().err == (
        f"error: api.sweep was called while a worker process imported {tmp_path / 'my_sweep.py'}: put the call "
        'under `if __name__ == "__main__":` (worker processes import the script that started them; docs/api.md)\n')
    assert list(tmp_path.iterdir()) == []
