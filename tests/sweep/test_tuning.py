"""Optuna tuning: trials are MLflow runs, pruning works, best params apply, studies are shared and resumable."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import optuna
import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli import cells
from bronchocli.config import load_config
from bronchocli.errors import ConfigError
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import search_runs
from bronchocli.sweep import tuning

MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
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
    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    write_config(tmp_path, steps=4, val_every=2, extra=SPACE)
    return tmp_path


def trial_states(cfg, name: str) -> list[str]:
    study = optuna.load_study(study_name=name, storage=tuning.storage_for(cfg))
    return [t.state.name for t in study.get_trials(deepcopy=False)]


def test_study_prunes_logs_every_trial_and_its_best_params_apply(project, cli):
    cfg = load_config(project / "experiments.yaml", overrides=[
        "tune.space={train.rot_weight: {type: categorical, choices: [0.0, 1000000.0]}}"])
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    # Trial 1's loss is 1e6 x the rotation error, far above trial 0's: the median pruner must prune it.
    study = tuning.tune(cfg, target, 4, progress=False,
                        enqueue=[{"train.rot_weight": 0.0}, {"train.rot_weight": 1000000.0}])
    trials = study.get_trials(deepcopy=False)
    assert tuning.finished(study) == 4
    assert trials[1].state == optuna.trial.TrialState.PRUNED
    assert study.best_trial.params == {"train.rot_weight": 0.0}
    client = client_for(cfg)
    runs = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "trial"})
    assert sorted(int(r.data.tags["trial"]) for r in runs) == [t.number for t in trials]
    by_trial = {int(r.data.tags["trial"]): r for r in runs}
    assert by_trial[1].info.status == "KILLED" and by_trial[1].data.tags["pruned"] == "true"
    assert all(r.data.tags["study"] == study.study_name for r in runs)
    assert all(t.user_attrs[tuning.ATTR_RUN] == by_trial[t.number].info.run_id for t in trials)
    # every trial nests under the study's one parent run, which ends with the best trial
    parents = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "study"})
    assert len(parents) == 1 and all(r.data.tags["mlflow.parentRunId"] == parents[0].info.run_id for r in runs)
    assert parents[0].info.status == "FINISHED" and parents[0].data.tags["best_trial"] == str(study.best_trial.number)
    assert parents[0].data.metrics["val_best.loss"] == pytest.approx(study.best_value)

    code, out, err = cli("train", "-c", str(project / "experiments.yaml"), *TARGET, "--use-tuned", study.study_name)
    assert code == 0, err
    cell_runs = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "cell"})
    assert len(cell_runs) == 1
    assert cell_runs[0].data.tags["hparams_source"] == f"optuna:{study.study_name}#{study.best_trial.number}"
    assert float(cell_runs[0].data.params["train.rot_weight"]) == 0.0

    code, out, err = cli("sweep", "-c", str(project / "experiments.yaml"), "--use-tuned", study.study_name,
                         "--only", "arch=baseline;rot_loss=mse;population=personalized")
    assert code == 0, err
    swept = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "cell"})
    assert len(swept) == 2 and {r.data.tags["hparams_source"] for r in swept} == {cell_runs[0].data.tags["hparams_source"]}
    sweep_parent = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "sweep"})
    assert len(sweep_parent) == 1 and sweep_parent[0].info.status == "FINISHED"  # the sweep's parent, ended with it
    swept_now = [r for r in swept if r.info.run_id != cell_runs[0].info.run_id]
    assert swept_now[0].data.tags["mlflow.parentRunId"] == sweep_parent[0].info.run_id
    assert "mlflow.parentRunId" not in cell_runs[0].data.tags  # `train` alone has no parent

    code, out, _ = cli("tune", "-c", str(project / "experiments.yaml"), "--study", study.study_name, "--show")
    assert code == 0 and "best trial" in out and "train.rot_weight" in out


def test_two_processes_share_one_study_and_an_interrupted_study_resumes(project):
    cfg = load_config(project / "experiments.yaml")
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    name = tuning.study_name(cfg, target)
    tuning.open_study(cfg, target)  # created once, as `tune` does
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-c", MAIN, "tune", *TARGET, "--trials", "3"]
    procs = [subprocess.Popen(cmd, cwd=project, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=600)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    states = trial_states(cfg, name)
    assert states.count("COMPLETE") + states.count("PRUNED") == 3, states

    # Interrupt a third process inside a trial that cannot finish first (a huge budget; the study name does not
    # depend on it): exactly that trial fails, then the same study resumes to 4 finished trials.
    ckpts = project / "runs" / "checkpoints"
    before = set(ckpts.glob("*")) if ckpts.is_dir() else set()
    proc = subprocess.Popen([*cmd[:-1], "4", "--set", "train.steps=100000", "--set", "train.val_every=1"],
                            cwd=project, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 300
    while not any((d / "last.pt").is_file() for d in (set(ckpts.glob("*")) if ckpts.is_dir() else set()) - before):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read()
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=300)
    assert proc.returncode == 130, out
    assert "Traceback" not in out
    states = trial_states(cfg, name)
    assert states.count("FAIL") == 1 and states.count("COMPLETE") + states.count("PRUNED") == 3, states
    again = subprocess.run([*cmd[:-1], "4"], cwd=project, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stdout + again.stderr
    states = trial_states(cfg, name)
    assert states.count("COMPLETE") + states.count("PRUNED") == 4, states


def test_bad_tune_space_is_one_clear_error(project):
    with pytest.raises(ConfigError) as exc:  # refused when the config loads, as `config` and `tune` both do
        load_config(project / "experiments.yaml", overrides=[
            "tune.space={train.lrr: {type: float, low: 1, high: 2}, model.dropout: {type: float, low: 0.5, high: 0.1}}"])
    assert "tune.space.train.lrr" in str(exc.value) and "needs low < high" in str(exc.value)
