"""Optuna tuning: trials are MLflow runs, pruning works, best params apply, studies are shared and resumable."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import optuna
import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli import cells, urls
from bronchocli.config import load_config
from bronchocli.errors import ConfigError
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import search_runs
from bronchocli.runs.views import text_figure
from bronchocli.sweep import StorageError, SweepStore, WorkerId
from bronchocli.sweep.tuning import studies, trial as tuning
from bronchocli.sweep.tuning import launch as trialrows
from bronchocli.sweep.tuning.rows import study_sweep

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
    study = optuna.load_study(study_name=name, storage=studies.storage_for(cfg))
    return [t.state.name for t in study.get_trials(deepcopy=False)]


def test_study_prunes_logs_every_trial_and_its_best_params_apply(project, cli):
    cfg = load_config(project / "experiments.yaml", overrides=[
        "tune.space={train.rot_weight: {type: categorical, choices: [0.0, 1000000.0]}}"])
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    # Trial 1's loss is 1e6 x the rotation error, far above trial 0's: the median pruner must prune it.
    study = trialrows.tune(cfg, target, 4, progress=False,
                        enqueue=[{"train.rot_weight": 0.0}, {"train.rot_weight": 1000000.0}])
    trials = study.get_trials(deepcopy=False)
    assert studies.finished(study) == 4
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
    # each trial is one row of the claims table, finished, naming its own run: no trial ran twice
    rows = SweepStore(cfg.paths.storage_url).rows(study_sweep(study.study_name))
    assert [r.cell_key for r in rows] == [f"trial-{i:04d}" for i in range(4)] and {r.state for r in rows} == {"finished"}
    assert sorted(r.run_id for r in rows) == sorted(r.info.run_id for r in runs)
    code, out, err = cli("status", "-c", str(project / "experiments.yaml"), "--sweep", study_sweep(study.study_name))
    # each trial row named as its run is: the trial slot, the model and its seed first
    assert code == 0 and out.count("finished") >= 4 and "trial 1 · Baseline MSE+MSE · s0" in out, out + err
    assert all(r.run_id in out for r in rows)
    code, out, err = cli("status", "-c", str(project / "experiments.yaml"))  # the config's status names the study
    assert code == 0 and f"study {study.study_name}: 4 trial row(s) (4 finished)" in out, out + err

    code, out, err = cli("train", "-c", str(project / "experiments.yaml"), *TARGET, "--use-tuned", study.study_name)
    assert code == 0, err
    cell_runs = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "cell"})
    assert len(cell_runs) == 1
    assert cell_runs[0].data.tags["hparams_source"] == f"optuna:{study.study_name}#{study.best_trial.number}"
    assert float(cell_runs[0].data.params["train.rot_weight"]) == 0.0

    code, out, err = cli("sweep", "run", "-c", str(project / "experiments.yaml"), "--use-tuned", study.study_name,
                         "--only", "arch=baseline;rot_loss=mse;population=personalized")
    assert code == 0, err
    swept = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "cell"})
    # the tuned cell FINISHED by `train` is the same cell: MLflow is the record, the sweep does not train it again
    assert [r.info.run_id for r in swept] == [cell_runs[0].info.run_id]
    sweep_parent = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "sweep"})
    assert len(sweep_parent) == 1 and sweep_parent[0].info.status == "FINISHED"  # the sweep's parent, ended with it
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
    proc.send_signal(signal.SIGHUP)  # the terminal closed: what Ctrl-C does (issue 49), the shell's code 129
    out, _ = proc.communicate(timeout=300)
    assert proc.returncode == 129, out
    assert "Traceback" not in out and "interrupted" in out
    client = client_for(cfg)
    (parent,) = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "study"})
    assert parent.info.status == "KILLED"  # an interrupted tune ends its study's parent run (issue 32, item 7)
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


def _study(n: int, params: tuple[str, ...]):
    """An in-memory study of ``n`` complete trials; the loss depends on train.lr only (model.dropout: noise)."""
    import math

    from optuna.distributions import FloatDistribution

    s = optuna.create_study(study_name=f"s{n}-{len(params)}")
    dists = {"train.lr": FloatDistribution(1e-5, 1e-2, log=True), "model.dropout": FloatDistribution(0.0, 0.5)}
    for i in range(n):
        values = {"train.lr": 10 ** (-5 + 3 * i / max(1, n - 1)), "model.dropout": (i * 7 % 12) / 24}
        s.add_trial(optuna.trial.create_trial(
            params={k: values[k] for k in params}, distributions={k: dists[k] for k in params},
            value=(math.log10(values["train.lr"]) + 3) ** 2, user_attrs={tuning.ATTR_RUN: f"run-{i}"}))
    return s


@pytest.mark.parametrize("n, params, caveat, plot", [
    (12, ("train.lr", "model.dropout"), None, True),  # enough trials: importances without a caveat
    (2, ("train.lr", "model.dropout"), "indicative only: 2 complete trials", True),  # two trials: with a caveat
    (6, ("train.lr",), "one searched parameter", False),  # one parameter: importance 1 by definition, no plot
])
def test_study_parent_shows_the_best_trial_and_importances_only_where_they_mean_something(
        tmp_path, n, params, caveat, plot):
    from bronchocli.config import Config
    from bronchocli.runs.parents import study_parent
    from bronchocli.sweep.summary import log_study

    cfg = Config(name="st").with_values({"runs.uri": f"sqlite:///{tmp_path / 'mlflow.db'}",
                                         "runs.artifacts": str(tmp_path / "art")})
    client = client_for(cfg)
    s = _study(n, params)
    parent = study_parent(client, cfg, experiment_id(client, cfg), s.study_name,
                          cells.make(arch="baseline", rot_loss="mse", population="personalized"))
    log_study(client, parent, studies.describe_study(s), studies.finished(s))
    run = client.get_run(parent)
    tags, metrics = run.data.tags, run.data.metrics
    best = s.best_trial
    assert tags["best_trial"] == str(best.number) and tags["best_run"] == f"run-{best.number}"
    assert {k: float(tags[f"best.{k}"]) for k in params} == pytest.approx(best.params)  # the best trial's values
    assert metrics["val_best.loss"] == pytest.approx(best.value) and metrics["trials.complete"] == n
    artifacts = {a.path for a in client.list_artifacts(parent)}
    assert ("param_importances.png" in artifacts) == plot
    if plot:  # train.lr decides the loss: the evaluator must find it far more important than the noise
        assert metrics["importance.train.lr"] > metrics["importance.model.dropout"]
    else:
        assert not any(k.startswith("importance.") for k in metrics)
    assert (caveat in tags["importances"]) if caveat else "importances" not in tags
    note = tags["mlflow.note.content"]  # the description says the same, best trial first
    assert f"Best: trial #{best.number}, val_best.loss {text_figure(best.value)}, with `train.lr` = " in note
    assert ("Importances: `train.lr`" in note) == plot and (caveat is None or caveat in note)


@pytest.mark.parametrize("objective", ["val_best.loss", "val_best.ratio.pos_l2", "cost.pairs_to_0.90"])
def test_tune_show_names_the_metric_the_study_minimises(tmp_path, monkeypatch, objective):
    """``tune --show`` labels the best value by the study's own objective metric, not always ``val_loss``."""
    from rich.console import Console

    from bronchocli.config import Config
    from bronchocli.sweep import entry

    s = _study(6, ("train.lr",))
    s.set_user_attr(studies.ATTR_OBJECTIVE, objective)
    monkeypatch.setattr(studies, "summary", lambda cfg, name: studies.describe_study(s))
    console = Console(record=True, width=200)
    info = entry.show_study(Config(name="st"), s.study_name, None, "table", console)
    out = " ".join(console.export_text().split())  # the title wraps over the table's width
    assert info["objective"] == objective
    assert f"best trial #{s.best_trial.number}: {objective} {s.best_value:.5g}" in out, out
    assert "val_loss" not in out


def test_a_stop_request_during_a_trials_evaluation_completes_it_and_starts_no_other(project, monkeypatch):
    """Issue 32, item 7: Ctrl-C in a trial's last steps (the run finishes its evaluation first) ends `tune` with
    that trial counted, no next trial started, and the study's parent run KILLED, not left RUNNING."""
    from bronchocli.runs.contract import RunInterrupted, RunResult
    from bronchocli.training import run as training_run

    cfg = load_config(project / "experiments.yaml")
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    started = []

    def evaluated_under_sigint(cfg, cell, **kw):
        started.append(cell.key)
        return RunResult(f"run{len(started)}", "FINISHED", {"val_best.loss": 1.0}, stop_requested=signal.SIGINT)

    monkeypatch.setattr(training_run, "run_cell", evaluated_under_sigint)
    with pytest.raises(RunInterrupted, match="trial #0 was evaluated"):
        trialrows.tune(cfg, target, 3, progress=False)
    assert len(started) == 1 and trial_states(cfg, tuning.study_name(cfg, target)) == ["COMPLETE"]
    client = client_for(cfg)
    (parent,) = search_runs(client, [experiment_id(client, cfg)], {"run_kind": "study"})
    assert parent.info.status == "KILLED"


def test_status_repair_ends_a_study_parent_whose_tune_was_killed(project, cli):
    from bronchocli.runs.parents import start_parent
    from bronchocli.runs.processes import TAG_PID

    cfg = load_config(project / "experiments.yaml")
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    parent = tuning.study_parent_or_none(cfg, target, "s")
    client = client_for(cfg)
    start_parent(client, parent)  # as `tune` does; then the process is SIGKILLed:
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    client.set_tag(parent, TAG_PID, str(dead.pid))
    code, out, err = cli("status", "-c", str(project / "experiments.yaml"), "--repair")
    assert code == 0 and f"repaired run {parent}" in out, out + err
    assert client.get_run(parent).info.status == "FAILED"


def test_a_lost_study_storage_is_rebuilt_from_the_trials_mlflow_records(project, monkeypatch):
    """Issue 32, item 2: with the study's database deleted, `tune` counts the FINISHED trial runs in MLflow and
    runs no trial again."""
    from bronchocli.runs.contract import RunResult
    from bronchocli.runs.records import cell_tags, log_metrics, log_params
    from bronchocli.training import run as training_run

    cfg = load_config(project / "experiments.yaml")
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    started = []

    def trial_run(trial_cfg, cell, *, extra_tags=None, run_id_callback=None, **_):
        client = client_for(trial_cfg)
        run_id = client.create_run(experiment_id(client, trial_cfg),
                                   tags=cell_tags(trial_cfg, cell, **(extra_tags or {}))).info.run_id
        run_id_callback(run_id)
        loss = trial_cfg.train.lr * 1000
        log_params(client, run_id, {"train.lr": str(trial_cfg.train.lr)})
        log_metrics(client, run_id, {"val_best.loss": loss})
        client.set_terminated(run_id, "FINISHED")
        started.append(run_id)
        return RunResult(run_id, "FINISHED", {"val_best.loss": loss})

    monkeypatch.setattr(training_run, "run_cell", trial_run)
    first = trialrows.tune(cfg, target, 2, progress=False)
    best = (first.best_trial.params, first.best_value)
    db = urls.sqlite_file(cfg.paths.storage_url)
    for path in (db, db.with_name(db.name + "-wal"), db.with_name(db.name + "-shm")):
        path.unlink(missing_ok=True)
    again = trialrows.tune(cfg, target, 2, progress=False)
    assert len(started) == 2 and studies.finished(again) == 2  # no trial ran again
    assert (again.best_trial.params, again.best_value) == best
    assert again.best_trial.user_attrs[tuning.ATTR_RUN] in started


def test_two_tune_workers_on_two_gpus_each_see_their_own_device(project):
    """`tune --workers 2` places its workers like a sweep's (issue 38, item 3): on two (faked) GPUs, each worker
    process sees one device, a different one, logs to its own file, and each trial records the worker that ran it;
    the workers are the local launcher's, driven by the sweep's driver over the study's claims rows."""
    from bronchocli.sweep.launchers import LocalLauncher

    cfg = load_config(project / "experiments.yaml")
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    study = trialrows.tune(cfg, target, 2, progress=False,
                        make_launcher=lambda lcfg, task, command: LocalLauncher(lcfg, gpus=["3", "5"], workers=2,
                                                                                  study=task))
    assert studies.finished(study) == 2
    logs = sorted((cfg.paths.sweep_logs / study_sweep(study.study_name)).glob("*.log"))
    seen = [re.search(r"tune worker of study .*, CUDA_VISIBLE_DEVICES=(\S+)", p.read_text()) for p in logs]
    assert len(logs) == 2 and sorted(m.group(1) for m in seen if m) == ["3", "5"], [p.read_text() for p in logs]
    workers = [WorkerId.parse(t.user_attrs[tuning.ATTR_WORKER]) for t in study.get_trials(deepcopy=False)]
    assert all(w is not None and w.gpu in ("3", "5") for w in workers)
    assert len({(w.pid, w.gpu) for w in workers}) == len({w.pid for w in workers})  # a process keeps its GPU
    rows = SweepStore(cfg.paths.storage_url).rows(study_sweep(study.study_name))
    assert {r.state for r in rows} == {"finished"} and len({r.run_id for r in rows}) == 2


def test_sweep_cancel_stops_a_study_whose_workers_a_detachable_launcher_started(project, cli):
    """`tune --launcher` with a launcher whose workers outlive the command (the test's subprocess launcher, as
    Slurm's): `sweep cancel --study NAME` finds the study's workers (its launcher is given the config named after
    the study's rows), stops them (the running trial's row is given back), and the watching `tune` ends 130 with
    the study's parent run KILLED and cancelled; the next `tune` un-cancels it."""
    from bronchocli.runs.parents import KIND_STUDY, find_parent
    from bronchocli.sweep.summary import TAG_CANCELLED

    kind = "subprocess_launcher:SubprocessLauncher"
    path = str(project / "experiments.yaml")
    cfg = load_config(path)
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    name = tuning.study_name(cfg, target)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": os.pathsep.join(sys.path)}
    tune = subprocess.Popen([sys.executable, "-c", MAIN, "tune", "-c", path, *TARGET, "--trials", "2", "--launcher",
                             kind, "--set", "train.steps=100000"], cwd=project, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    store, end = SweepStore(cfg.paths.storage_url), time.monotonic() + 300

    def training() -> bool:  # an event the test waits for (a trial trains); the limit guards a hang
        try:
            return any(r.state == "running" and r.run_id for r in store.rows(study_sweep(name)))
        except StorageError:  # the table not created yet, or SQLite busy with the workers' writes
            return False

    while not training():
        assert tune.poll() is None and time.monotonic() < end, tune.stdout.read()
        time.sleep(0.05)
    code, out, err = cli("sweep", "cancel", "-c", path, "--study", name, "--launcher", kind)
    assert code == 0 and "cancelled subprocess job(s)" in out, out + err
    out, _ = tune.communicate(timeout=300)
    assert tune.returncode == 130 and "was cancelled" in out and "Traceback" not in out, out
    assert f"study {name} was cancelled (`bronchopose sweep cancel --study {name}`): nothing is submitted again; " \
           "the same `bronchopose tune` command resumes it" in " ".join(out.split()), out  # not `sweep run`
    end = time.monotonic() + 300  # the watch ends at the cancel; the stopping workers checkpoint, then give back
    while {r.state for r in store.rows(study_sweep(name))} != {"pending"}:  # each stopped worker its trial's row
        assert time.monotonic() < end, store.rows(study_sweep(name))
        time.sleep(0.05)
    client = client_for(cfg)
    parent = client.get_run(find_parent(client, experiment_id(client, cfg), KIND_STUDY, name))
    assert parent.info.status == "KILLED" and TAG_CANCELLED in parent.data.tags
    assert "FAIL" in trial_states(cfg, name) and "COMPLETE" not in trial_states(cfg, name)
    from subprocess_launcher import SubprocessLauncher

    while SubprocessLauncher(trialrows.launcher_config(cfg, name)).active():  # the stopped workers exit
        assert time.monotonic() < end
        time.sleep(0.05)
    code, out, err = cli("sweep", "cancel", "-c", path, "--study", name, "--launcher", kind)
    assert code == 0 and f"no subprocess job of sweep {study_sweep(name)} is queued or running" in out, out + err


def test_a_budgeted_ratio_objective_trains_every_trial_the_same_pairs_and_minimises_the_val_ratio(project):
    """tune.budget_pairs: trials searching the batch size see the same pairs (steps = budget / pairs per step),
    validate at the same pairs seen and report there; tune.objective val_ratio returns val_best.ratio.pos_l2."""
    cfg = load_config(project / "experiments.yaml", overrides=[
        "tune.space={train.batch_size: {type: categorical, choices: [4, 8]}}",
        "tune.objective=val_ratio", "tune.budget_pairs=32", "tune.pruner=none", "train.batch_size=4",
        "train.val_every=4"])  # the base config validates every 4 x 4 = 16 pairs
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    study = trialrows.tune(cfg, target, 2, progress=False,
                          enqueue=[{"train.batch_size": 4}, {"train.batch_size": 8}])
    trials = study.get_trials(deepcopy=False)
    assert [t.state.name for t in trials] == ["COMPLETE", "COMPLETE"]
    assert study.user_attrs["objective"] == "val_best.ratio.pos_l2"
    client = client_for(cfg)
    for t, steps, per_step in zip(trials, (8, 4), (4, 8)):
        run = client.get_run(t.user_attrs[tuning.ATTR_RUN])
        assert run.data.metrics["train.steps"] == steps
        assert run.data.metrics["train.pairs_seen"] == 32  # the budget, whatever the batch
        assert t.value == pytest.approx(run.data.metrics["val_best.ratio.pos_l2"])
        # reported to Optuna at pairs seen, every 16 pairs, whatever the batch
        assert sorted(t.intermediate_values) == [16, 32]
        ratios = [m.value for m in client.get_metric_history(run.info.run_id, "val.ratio.pos_l2")]
        assert sorted(t.intermediate_values.values()) == pytest.approx(sorted(ratios))
        assert [m.step * per_step for m in client.get_metric_history(run.info.run_id, "val.ratio.pos_l2")] == [16, 32]


def test_the_cost_objective_stops_each_trial_at_the_target_and_returns_the_pairs_it_took(project):
    cfg = load_config(project / "experiments.yaml", overrides=[
        "tune.space={train.lr: {type: float, low: 1.0e-4, high: 1.0e-3, log: true}}",
        "tune.objective=cost", "tune.budget_pairs=32", "tune.pruner=none", "train.batch_size=4", "train.val_every=2"])
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    study = trialrows.tune(cfg, target, 1, progress=False)
    (t,) = study.get_trials(deepcopy=False)
    run = client_for(cfg).get_run(t.user_attrs[tuning.ATTR_RUN])
    m, p = run.data.metrics, run.data.params
    assert study.user_attrs["objective"] == "cost.pairs_to_0.90"
    assert p["train.stop_at_ratio"] == "0.9"  # the trial ends at the target
    if "cost.pairs_to_0.90" in m:  # learned: the pairs it took, and it stopped there
        assert t.value == m["cost.pairs_to_0.90"] == m["train.pairs_seen"] and run.data.tags["stop_reason"] == "target"
    else:  # did not: its whole budget, scaled up by how far it stayed from the target
        assert m["train.pairs_seen"] == 32 and m["val_best.ratio.pos_l2"] > 0.9
        assert t.value == pytest.approx(32 * (1 + m["val_best.ratio.pos_l2"] - 0.9))


def test_a_study_keeps_its_objective(project):
    cfg = load_config(project / "experiments.yaml", overrides=["tune.objective=val_ratio"])
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    tuning.open_study(cfg, target)
    other = load_config(project / "experiments.yaml")
    with pytest.raises(ConfigError, match="minimises val_best.ratio.pos_l2 already"):
        tuning.open_study(other, target)


def test_tune_with_an_unreachable_storage_fails_in_one_line_before_any_dataset_is_rendered(tmp_path, cli):
    """Cheap checks first (issue 47.6): the storage answers before the dataset (absent here) would be rendered."""
    write_config(tmp_path)  # dataset.root data/tiny does not exist: tune would render it first
    code, out, err = cli("tune", "-c", tmp_path / "experiments.yaml", "-a", "baseline", "-l", "mse",
                         "-P", "personalized", "-n", "1", "-q", "--storage", "postgresql://bob:hunter2@127.0.0.1:1/db")
    assert code == 2, (out, err)
    assert "Connection refused" in err and "hunter2" not in err and "Traceback" not in err + out
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "data").exists()  # nothing rendered, nothing created


def test_a_timeout_already_past_starts_no_trial_and_gives_every_row_back(project):
    """`tune --timeout`: once the deadline passed a worker claims a row only to give it back, no trial starts, and
    the rows stay claimable for the next `tune` (which runs them)."""
    cfg = load_config(project / "experiments.yaml", overrides=["name=timeout-study"])
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    study = trialrows.tune(cfg, target, 2, timeout=1e-9, progress=False)
    assert study.get_trials(deepcopy=False) == []
    rows = SweepStore(cfg.paths.storage_url).rows(study_sweep(study.study_name))
    assert [r.state for r in rows] == ["pending", "pending"] and all(r.attempts == 0 for r in rows)
    again = trialrows.tune(cfg, target, 2, progress=False)
    assert studies.finished(again) == 2


def test_a_study_storage_that_refuses_writes_is_one_line_as_the_claims_table_says_it(project, cli, monkeypatch):
    """Issue 60, item 2: Optuna's StorageInternalError (here a read-only SQLite file, as a user without write
    permission meets it) is one line naming the storage and the database's reason, exit 2, no traceback."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    def readonly(self, *args, **kw):
        try:
            raise OperationalError("INSERT INTO studies", {}, sqlite3.OperationalError(
                "attempt to write a readonly database"))
        except OperationalError as exc:
            raise optuna.exceptions.StorageInternalError("An exception is raised during the commit.") from exc

    monkeypatch.setattr(optuna.storages.RDBStorage, "create_new_study", readonly)
    code, out, err = cli("tune", "-c", project / "experiments.yaml", *TARGET, "-n", "1")
    db = project / "runs" / "sweep.db"
    assert code == 2 and err.strip() == f"error: study storage sqlite:///{db}: attempt to write a readonly database", \
        (out, err)


def test_the_default_tune_goes_through_the_driver_and_the_launcher_runs_its_one_worker_here(project, monkeypatch):
    """Issue 58: on a machine without a GPU `tune` drives its rows as a cluster's (``launch.drive`` with a
    launcher); running the one worker in this process is the local launcher's choice, not the driver's — with two
    workers the same launcher starts processes."""
    from bronchocli.sweep import launch
    from bronchocli.sweep.tuning import worker as trialwork
    from bronchocli.sweep.launchers.local import InProcess, LocalLauncher, LocalProcesses
    from bronchocli.sweep.tuning.rows import StudyTask

    seen: dict = {}
    real_drive = launch.drive

    def drive(walk, launcher, *args, **kw):
        seen["launcher"] = launcher
        return real_drive(walk, launcher, *args, **kw)

    def work(cfg, store, task, **kw):  # the worker's loop itself is tested above: here, where it runs
        seen.update(pid=os.getpid(), study=task.study, progress=kw["progress"])
        return 0, None

    monkeypatch.setattr(launch, "drive", drive)
    monkeypatch.setattr(trialwork, "work_trials", work)
    cfg = load_config(project / "experiments.yaml")
    target = cells.make(arch="baseline", rot_loss="mse", population="personalized")
    trialrows.tune(cfg, target, 2, study="here", progress=True)
    launcher = seen["launcher"]
    assert isinstance(launcher, LocalLauncher) and isinstance(launcher.processes, InProcess)
    assert launcher.describe() == "in this process"
    assert seen == {"launcher": launcher, "pid": os.getpid(), "study": "here", "progress": True}
    two = LocalLauncher(cfg, study=StudyTask("here", cfg.name), workers=2, gpus="none")
    assert type(two.processes) is LocalProcesses
