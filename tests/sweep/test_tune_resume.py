"""Issue 50, deliver 3: a tune trial stopped by Ctrl-C is resumed from its checkpoint by the next `tune` of the
study (same parameters, same MLflow run, from the checkpoint's step), and `sweep gc` lists a trial's checkpoint
as kept while its study can resume it and reclaims it once no trial will."""

from __future__ import annotations

import os
import signal

import optuna
import pytest
from optuna.distributions import FloatDistribution
from optuna.trial import TrialState, create_trial
from test_housekeeping import new_run
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli import cells
from bronchocli.config import load_config
from bronchocli.io import fmt_bytes, folder_bytes
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.contract import RunInterrupted, resume_file
from bronchocli.runs.parents import study_parent
from bronchocli.runs.records import TAG_PARENT
from bronchocli.sweep import SweepStore
from bronchocli.sweep.tuning import studies, trial as tuning
from bronchocli.sweep.tuning import launch as trialrows
from bronchocli.sweep.tuning.rows import study_sweep
from bronchocli.sweep.tuning.resume import ATTR_RESUME_CELL, ATTR_RESUME_RUN, ATTR_RESUMES

SPACE = {"train.lr": {"type": "float", "low": 1.0e-5, "high": 1.0e-3, "log": True}}
TARGET = dict(arch="baseline", rot_loss="mse", population="personalized")


def study_trials(cfg, name: str) -> list:
    return optuna.load_study(study_name=name, storage=studies.storage_for(cfg)).get_trials(deepcopy=False)


@pytest.mark.heavy  # trains twice
def test_a_trial_stopped_by_ctrl_c_is_resumed_from_its_checkpoint_by_the_next_tune(tmp_path, monkeypatch, cli):
    from bronchocli.training import run as training_run

    write_tiny_dataset(tmp_path / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
    path = write_config(tmp_path, steps=4, val_every=2, extra="tune:\n  startup_trials: 1\n  warmup_validations: 0\n"
                        "  space:\n    train.lr: {type: float, low: 1.0e-5, high: 1.0e-3, log: true}\n")
    cfg = load_config(path)
    target = cells.make(**TARGET)
    name = tuning.study_name(cfg, target)
    real, resumed = training_run.run_cell, []

    def first_run_interrupted(trial_cfg, cell, **kw):  # the real run; Ctrl-C lands at the first run's step 2
        resumed.append(kw.get("resume"))
        if len(resumed) == 1:
            report = kw["on_validation"]

            def on_validation(step, values):
                report(step, values)
                if step == 2:
                    os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C delivers; run_cell's own handler takes it
            kw["on_validation"] = on_validation
        return real(trial_cfg, cell, **kw)

    monkeypatch.setattr(training_run, "run_cell", first_run_interrupted)
    with pytest.raises(RunInterrupted, match="SIGINT received at step 3/4"):
        trialrows.tune(cfg, target, 2, progress=False)
    stopped, waiting = study_trials(cfg, name)
    rows = SweepStore(cfg.paths.storage_url).rows(study_sweep(name))
    assert [(r.state, r.attempts) for r in rows] == [("pending", 0), ("pending", 0)]  # its row given back
    assert (stopped.state, waiting.state) == (TrialState.FAIL, TrialState.WAITING)
    run_id = stopped.user_attrs[tuning.ATTR_RUN]
    assert waiting.user_attrs == {ATTR_RESUME_RUN: run_id, ATTR_RESUMES: 0,
                                  ATTR_RESUME_CELL: stopped.user_attrs["cell"]}
    assert waiting.system_attrs["fixed_params"] == stopped.params  # the same parameters
    client = client_for(cfg)
    assert client.get_run(run_id).info.status == "KILLED"
    ckpt = resume_file(cfg, run_id)
    size = folder_bytes(ckpt.parent)

    code, out, err = cli("sweep", "gc", "-c", str(path))  # kept, and listed with why
    assert code == 0, err
    assert ckpt.is_file() and f"kept {fmt_bytes(size)}: {ckpt.parent} (the study can resume it: trial #1 of study " \
        f"{name} continues it" in out, out
    assert "gc: freed 0 B in 0 checkpoint folder(s)" in out

    study = trialrows.tune(cfg, target, 2, progress=False)  # the same command again
    trials = study.get_trials(deepcopy=False)
    assert [t.state for t in trials[:2]] == [TrialState.FAIL, TrialState.COMPLETE]
    assert trials[2].state in (TrialState.COMPLETE, TrialState.PRUNED) and studies.finished(study) == 2
    assert resumed == [None, run_id, None]  # trial 1 continued the stopped run; trial 2 is a fresh one
    again = trials[1]
    assert again.params == stopped.params and again.user_attrs[tuning.ATTR_RUN] == run_id
    rows = SweepStore(cfg.paths.storage_url).rows(study_sweep(name))  # one row per trial that counts
    assert [(r.state, r.run_id) for r in rows] == [("finished", run_id), ("finished", trials[2].user_attrs[tuning.ATTR_RUN])]
    assert sorted(again.intermediate_values) == [2, 4]  # step 2: the stopped trial's report, copied
    assert again.intermediate_values[2] == stopped.intermediate_values[2]
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED" and "failure_reason" not in run.data.tags
    assert (run.data.tags["trial"], run.data.tags["resumed_trial"]) == ("1", "0")
    assert [(m.step, m.value) for m in client.get_metric_history(run_id, "resumed_from_step")] == [(3, 3.0)]
    assert sorted(m.step for m in client.get_metric_history(run_id, "val_loss")) == [2, 4]
    assert again.value == pytest.approx(run.data.metrics["val_best.loss"])
    assert not ckpt.exists()  # a finished run's checkpoint goes with it
    code, out, err = cli("sweep", "gc", "-c", str(path))
    assert code == 0 and "kept" not in out and run_id not in out, out + err


@pytest.mark.heavy  # MLflow and Optuna stores, `sweep gc` twice (as tests/sweep/test_housekeeping.py)
def test_gc_keeps_a_trials_checkpoint_while_its_study_can_resume_it_and_reclaims_it_after(make_config, cli):
    cfg = make_config(tune={"space": SPACE})
    target = cells.make(**TARGET)
    cell = cfg.cell(**TARGET)
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    dists = {"train.lr": FloatDistribution(1e-5, 1e-3, log=True)}
    parents, runs = {}, {}
    for name, status in (("open", "KILLED"), ("done", "FINISHED")):  # the last `tune` interrupted / reached its trials
        parents[name] = study_parent(client, cfg, exp, name, target)
        client.set_terminated(parents[name], status)
        tuning.open_study(cfg, target, study=name)

    def stopped_trial(key: str, study: str, nbytes: int, lr: float, resumer: TrialState | None) -> None:
        """A KILLED trial run with its checkpoint, its FAIL trial, and (unless None) a trial that resumes it."""
        runs[key] = new_run(cfg, cell, "KILLED", nbytes, run_kind="trial", study=study,
                            **{TAG_PARENT: parents.get(study, "0" * 32)})
        if study not in parents:
            return
        s = optuna.load_study(study_name=study, storage=studies.storage_for(cfg))
        s.add_trial(create_trial(state=TrialState.FAIL, params={"train.lr": lr}, distributions=dists,
                                 user_attrs={tuning.ATTR_RUN: runs[key]}))
        attrs = {ATTR_RESUME_RUN: runs[key], ATTR_RESUMES: len(s.trials) - 1, ATTR_RESUME_CELL: cell.key}
        if resumer == TrialState.WAITING:
            s.enqueue_trial({"train.lr": lr}, user_attrs=attrs)
        elif resumer is not None:  # it ran, without the checkpoint (another machine, another config)
            s.add_trial(create_trial(state=resumer, params={"train.lr": lr}, distributions=dists, value=0.5,
                                     user_attrs={**attrs, tuning.ATTR_RUN: "f" * 32}))

    stopped_trial("resumable", "open", 1000, 1e-4, TrialState.WAITING)
    stopped_trial("never_handed_on", "open", 3000, 2e-4, None)  # stopped before this existed: the case
    stopped_trial("ran_without", "open", 5000, 3e-4, TrialState.COMPLETE)
    stopped_trial("study_done", "done", 7000, 4e-4, TrialState.WAITING)
    stopped_trial("other_storage", "elsewhere", 11000, 5e-4, None)  # a study this storage.url does not hold
    folders = {k: resume_file(cfg, r).parent for k, r in runs.items()}
    sizes = {k: folder_bytes(f) for k, f in folders.items()}
    path = str(cfg.paths.base / "experiments.yaml")

    code, out, err = cli("sweep", "gc", "-c", path, "--dry-run")
    assert code == 0, err
    assert all(f.is_dir() for f in folders.values())  # nothing removed
    expect = {"resumable": "kept {}: {} (the study can resume it: trial #1 of study open continues it",
              "never_handed_on": "would free {}: {} (trial #2 of study open ended FAIL; no trial resumes it)",
              "ran_without": "would free {}: {} (trial #4 of study open (COMPLETE) ran without it)",
              "study_done": "would free {}: {} (study done done (its parent run FINISHED) without resuming it",
              "other_storage": "kept {}: {} (study elsewhere is not in storage.url "}
    for key, line in expect.items():
        assert line.format(fmt_bytes(sizes[key]), folders[key]) in out, (key, out)
    gone = ("never_handed_on", "ran_without", "study_done")
    total = fmt_bytes(sum(sizes[k] for k in gone))
    assert f"gc --dry-run: would free {total} in 3 checkpoint folder(s)" in out

    code, out, err = cli("sweep", "gc", "-c", path)
    assert code == 0, err
    assert sorted(p.name for p in cfg.paths.checkpoints.iterdir()) == sorted([runs["resumable"], runs["other_storage"]])
    assert f"gc: freed {total} in 3 checkpoint folder(s)" in out
    assert resume_file(cfg, runs["resumable"]).is_file() and resume_file(cfg, runs["other_storage"]).is_file()
