"""A staged sweep (the paper's protocol): stage 2 and 3 take the top combinations of stage 1 by a validation
metric, never a test one; every cell runs exactly once, across stages; the selection is recorded and shown."""

from __future__ import annotations

import json

import pytest
from sweep_fakes import FAKE, calls, runs_by_cell
from tinydata import write_tiny_dataset

from bronchocli.config import Config
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import search_runs
from bronchocli.sweep import SweepStore
from bronchocli.sweep import plan as plan_module
from bronchocli.sweep.plan import plan_key, plan_stages

STAGES = [
    {"name": "personalized", "grid": {"arch": ["baseline", "lstm", "convlstm"], "rot_loss": ["mse", "ce"],
                                      "population": ["personalized"]}},
    {"name": "cross-subject", "select": {"top": 2, "by": "val_best.pos_l2"},
     "grid": {"population": ["cross-subject"], "folds": ["p00"]}},
    {"name": "sota", "source": "personalized", "select": {"top": 1},
     "grid": {"population": ["personalized"]}, "add": [{"arch": "offsetnet", "rot_loss": "mse"}]},
]
VALIDATION = {("lstm", "ce"): 0.1, ("convlstm", "mse"): 0.2, ("baseline", "mse"): 0.6, ("baseline", "ce"): 0.7,
              ("lstm", "mse"): 0.8, ("convlstm", "ce"): 0.9}


@pytest.fixture
def project(make_config, tmp_path, fake_dir):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    for (arch, loss), value in VALIDATION.items():
        (fake_dir / f"val-{arch}-{loss}").write_text(str(value))
    # No takeover is wanted here (each cell's runner is counted): a 2 s cut-off let a worker starved by a loaded
    # machine lose its claim and the cell run twice (one FINISHED run, two runner calls).
    return make_config(stages=STAGES, grid={"seed": [0, 1], "folds": ["p00"]}, sweep={"stale_after_s": 60.0})


def count_calls(monkeypatch, owner, name: str) -> list[int]:
    """Count the calls of ``owner.name`` in this process (a one-element list)."""
    real, seen = getattr(owner, name), [0]

    def counted(*args, **kw):
        seen[0] += 1
        return real(*args, **kw)

    monkeypatch.setattr(owner, name, counted)
    return seen


def test_stages_select_by_validation_and_run_each_cell_once(cli, project, fake_dir):
    path = str(project.paths.base / "experiments.yaml")
    code, out, _ = cli("sweep", "plan", "-c", path)
    assert code == 0 and "12 cells" in out and "cells known once stage personalized is done" in out

    with pytest.MonkeyPatch.context() as mp:
        patients = count_calls(mp, plan_module, "planned_patients")
        selections = count_calls(mp, SweepStore, "selection")
        code, out, err = cli("sweep", "-c", path, "--workers", "2", *FAKE)
    assert code == 0, out + err
    # One walk in the sweep's process: the patients read once; each selecting stage's selection read when
    # planned, when decided and once more by the settling (another process may have recorded it meanwhile).
    assert patients == [1] and selections[0] <= 3 * 2, (patients, selections)
    # Poisoned on purpose: the test metric ranks these two last; the validation metric ranks them first.
    assert "top 2 of stage personalized by val_best.pos_l2" in out and "lstm/ce 0.1" in out and "convlstm/mse 0.2" in out
    store = SweepStore(project.paths.storage_url)
    stages = {sp.stage.name: sp for sp in plan_stages(project, store)}
    assert {(c.arch, c.rot_loss, c.fold) for c in stages["cross-subject"].cells} == {
        ("lstm", "ce", "p00"), ("convlstm", "mse", "p00")}
    assert {(c.arch, c.rot_loss) for c in stages["sota"].cells} == {("lstm", "ce"), ("offsetnet", "mse")}
    assert len(stages["cross-subject"].cells) == 4 and len(stages["sota"].cells) == 4  # x 2 seeds
    # Exactly once: the sota stage reuses stage 1's lstm/ce runs; 12 + 4 + 2 distinct cells, one run each.
    finished = runs_by_cell(project)
    assert len(finished) == 18 and set(finished.values()) == {1}
    assert all(calls(c.key) == 1 for c in stages["sota"].cells)

    client = client_for(project)
    exp = experiment_id(client, project)
    selections = search_runs(client, [exp], {"run_kind": "selection"})
    assert sorted(r.data.tags["stage"] for r in selections) == ["cross-subject", "sota"]
    parent = search_runs(client, [exp], {"run_kind": "sweep"})
    assert len(parent) == 1 and {r.data.tags["mlflow.parentRunId"] for r in selections} == {parent[0].info.run_id}
    rec = next(r for r in selections if r.data.tags["stage"] == "cross-subject")
    assert rec.data.tags["plan_key"] == plan_key(project)
    payload = json.loads(open(client.download_artifacts(rec.info.run_id, "selection.json")).read())
    assert payload["selected"] == [{"arch": "lstm", "rot_loss": "ce"}, {"arch": "convlstm", "rot_loss": "mse"}]
    assert [e["runs"] for e in payload["ranked"]] == [2] * 6  # every combination, both seeds, with its value
    check_parent(client, parent[0].info.run_id, stages)

    code, out, _ = cli("status", "-c", path)
    assert code == 0 and "stage cross-subject: top 2 of stage personalized by val_best.pos_l2" in out
    code, out, _ = cli("sweep", "-c", path, *FAKE)  # all done: nothing runs again
    assert code == 0 and "nothing left to run" in out and len(runs_by_cell(project)) == 18


def check_parent(client, run_id: str, stages) -> None:
    """The sweep's parent states what ran (stages, their cells and selections; not the config's grid lists)
    and the outcome (cells finished/failed, the best cell per stage by validation with its test figure)."""
    run = client.get_run(run_id)
    params, metrics, tags = run.data.params, run.data.metrics, run.data.tags
    assert run.info.status == "FINISHED"
    assert not any(k.startswith(("grid.", "stages.")) for k in params), sorted(params)  # no config grid lists
    assert params["stages"] == "personalized,cross-subject,sota" and params["cells"] == "18"
    assert {k: params[f"stage.personalized.{k}"] for k in ("cells", "arch", "rot_loss", "population", "seed")} == {
        "cells": "12", "arch": "baseline,lstm,convlstm", "rot_loss": "mse,ce", "population": "personalized",
        "seed": "0,1"}
    assert "stage.personalized.fold" not in params  # no personalized cell has a held-out patient
    assert params["stage.cross-subject.select"] == "top 2 of personalized by val_best.pos_l2 over arch,rot_loss"
    assert params["stage.cross-subject.selected"] == "lstm/ce,convlstm/mse"
    assert (params["stage.cross-subject.arch"], params["stage.cross-subject.fold"]) == ("lstm,convlstm", "p00")
    assert params["stage.sota.selected"] == "lstm/ce" and params["stage.sota.arch"] == "lstm,offsetnet"
    assert "lstm/ce 0.1" in tags["selection.cross-subject"] and "by val_best.pos_l2" in tags["selection.sota"]
    assert (metrics["cells.planned"], metrics["cells.finished"], metrics["cells.failed"]) == (18, 18, 0)
    assert metrics["best.personalized.val_best.pos_l2"] == pytest.approx(0.1)  # lstm/ce, the validation's best
    assert metrics["best.personalized.pair.pos_l2.mean"] == pytest.approx(9.9)  # its test figure (fake: 10 - val)
    assert tags["best.personalized.cell"].startswith("lstm/ce/personalized/")
    best = client.get_run(tags["best.personalized.run"])
    assert (best.data.tags["arch"], best.data.tags["rot_loss"]) == ("lstm", "ce")
    values = {c.label: v for c in stages["sota"].cells
              for v in [search_runs(client, [run.info.experiment_id], {"cell_key": c.key})[0]
                        .data.metrics["val_best.pos_l2"]]}
    assert metrics["best.sota.val_best.pos_l2"] == pytest.approx(min(values.values()))  # the stage's own minimum
    assert tags["best.sota.cell"] == min(values, key=lambda k: (values[k], k))
    note = tags["mlflow.note.content"]  # the run page's description: counts, then each stage, headline first
    assert note.startswith("Sweep **t**: 18 cells planned, 18 finished, 0 failed.")
    assert ("- **personalized**: 12 cells; best by validation: lstm/ce/personalized/s0/world (pair.pos_l2.mean 9.900, "
            "val_best.pos_l2 0.1000)") in note
    assert "- **cross-subject**: 4 cells, top 2 of stage personalized by val_best.pos_l2" in note


def test_a_later_stage_waits_while_its_source_is_incomplete(cli, project):
    path = str(project.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "-c", path, "--only", "arch=baseline", *FAKE)
    assert code == 0, out + err
    assert "stage cross-subject waits: 8 cell(s) of stage personalized are not done" in out
    assert SweepStore(project.paths.storage_url).selection(project.name, plan_key(project), "cross-subject") is None


@pytest.mark.parametrize("stages, message", [
    ([{"name": "a", "select": {"top": 1}}], "the first stage has no earlier stage"),
    ([{"name": "a"}, {"name": "b", "select": {"by": "pair.pos_l2.mean"}}], "must be a validation metric"),
    ([{"name": "a"}, {"name": "a"}], "used twice"),
    ([{"name": "a"}, {"name": "b", "source": "c", "select": {}}], "must name an earlier stage"),
    ([{"name": "a", "grid": {"colour": ["red"]}}], "unknown grid key"),
    ([{"name": "a", "grid": {"arch": ["resnet"]}}], "stages[0] (a).grid.arch"),
])
def test_bad_stages_are_rejected_with_the_reason(stages, message):
    with pytest.raises(Exception) as exc:
        Config.model_validate({"name": "t", "stages": stages})
    assert message in str(exc.value)


def test_the_paper_profile_encodes_the_three_experiments(repo):
    from bronchocli.config import load_config

    cfg = load_config(repo / "experiments.yaml", profile="paper")
    names = [s.name for s in cfg.stages]
    assert names == ["personalized", "cross-subject", "sota"]
    first, second, third = cfg.stages
    assert set(first.stage_grid(cfg.grid).arch) == {"baseline", "lstm", "convlstm", "conv3d"}
    assert second.select.top == 3 and second.stage_grid(cfg.grid).population == ["cross-subject"]
    assert third.select.top == 1 and third.add == [{"arch": "offsetnet", "rot_loss": "mse"}]
    assert second.select.by.startswith("val_best.") and third.source == "personalized"
