"""Run collection: one query, the config's cells only, latest FINISHED per cell, clear errors."""

from __future__ import annotations

import pytest
from report_fakes import EXPERIMENT, SEEDS, SWEEP

from bronchocli.errors import BronchoError
from bronchocli.reporting.collect import RunRecord, collect_runs, index_runs
from bronchocli.reporting.scope import PlanView

BASE = {"arch": "lstm", "rot_loss": "ce", "population": "personalized", "fold": "", "seed": "0",
        "pose_frame": "world", "train_trajectories": ""}


def _rec(run_id: str, status: str = "FINISHED", start: int = 0, key: str = "k0", **tags: str) -> RunRecord:
    return RunRecord(run_id, status, start, {**BASE, "cell_key": key, **tags}, {})


def _ident(**tags: str) -> tuple[str, ...]:
    return tuple({**BASE, **tags}[k] for k in BASE)


def test_latest_finished_run_wins_and_the_others_are_duplicates():
    index = index_runs([_rec("old", start=1), _rec("new", start=3), _rec("failed", "FAILED", start=9)], "s", "e")
    (ident, kept), = index.runs.items()
    assert kept.run_id == "new"
    assert [r.run_id for r in index.duplicates[ident]] == ["old"]
    assert index.unfinished == {}


def test_cells_with_only_unfinished_runs_are_remembered():
    index = index_runs([_rec("k", "KILLED"), _rec("f", "FAILED", arch="conv3d")], "s", "e")
    assert index.runs == {}
    assert [r.run_id for r in index.not_finished(_ident(arch="conv3d"))] == ["f"]


def test_config_mode_keeps_only_the_config_keys_and_counts_the_rest():
    plan = PlanView({"grid": [_ident(), _ident(arch="conv3d")]}, {_ident(): "k0", _ident(arch="conv3d"): "k1"})
    runs = [_rec("mine", key="k0", start=1), _rec("stale", key="old-key", start=5),
            _rec("stale-conv3d", key="old-key-2", arch="conv3d", start=5)]
    index = index_runs(runs, "s", "e", plan=plan)
    assert {i: r.run_id for i, r in index.runs.items()} == {_ident(): "mine"}
    assert index.other_configs == 2
    assert index.notes == ["config: left out 2 run(s) of sweep 's' (2 FINISHED) whose cell_key is not a cell of "
                           "this config (made under another config); --include-other-configs uses them"]
    both = index_runs(runs, "s", "e", plan=plan, include_other_configs=True)
    assert {r.run_id for r in both.runs.values()} == {"stale", "stale-conv3d"}  # the latest per identity
    assert any("mixes configs" in n for n in both.notes)


def test_sweep_mode_warns_when_one_cell_has_runs_of_several_configs():
    index = index_runs([_rec("a", key="k0", start=1), _rec("b", key="k9", start=2)], "s", "e")
    assert [r.run_id for r in index.runs.values()] == ["b"]
    assert len(index.notes) == 1 and "mixes configs: 1 cell(s)" in index.notes[0]


def test_mixed_pose_frames_default_to_world_and_say_so():
    runs = [_rec("w"), _rec("c", pose_frame="camera")]
    index = index_runs(runs, "s", "e")
    assert index.pose_frame == "world" and {r.run_id for r in index.runs.values()} == {"w", "c"}
    assert index.notes == ["pose frame: the runs span camera, world; the main tables use world (--pose-frame "
                           "chooses; the frames table compares both)"]
    assert [r.run_id for r in index.select("personalized", "lstm", "ce")] == ["w"]
    chosen = index_runs(runs, "s", "e", pose_frame="camera")
    assert [r.run_id for r in chosen.select("personalized", "lstm", "ce")] == ["c"] and chosen.notes == []


def test_several_training_set_sizes_use_the_default_one_in_the_tables():
    runs = [_rec("t2", train_trajectories="2"), _rec("t8", train_trajectories="8"), _rec("full")]
    index = index_runs(runs, "s", "e")
    assert index.train_size == "" and index.sizes() == ["2", "8", ""]
    assert [r.run_id for r in index.select("personalized", "lstm", "ce")] == ["full"]
    no_default = index_runs(runs[:2], "s", "e")
    assert no_default.train_size == "8"  # else the largest


def test_replicas_and_select_cover_folds_and_seeds():
    runs = [_rec(f"{f}{s}", population="cross-subject", fold=f, seed=s) for f in ("p01", "p00") for s in ("10", "2")]
    index = index_runs(runs, "s", "e")
    assert index.replicas("cross-subject") == [("p00", "2"), ("p00", "10"), ("p01", "2"), ("p01", "10")]
    assert [r.run_id for r in index.select("cross-subject", "lstm", "ce")] == ["p002", "p0010", "p012", "p0110"]


class CountingClient:
    """The real MlflowClient, counting its search_runs calls."""

    def __init__(self, client):
        self.client, self.searches = client, 0

    def search_runs(self, *args, **kwargs):
        self.searches += 1
        return self.client.search_runs(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.client, name)


def test_collect_runs_makes_one_query_for_the_runs_one_for_deleted_ones_and_ignores_trials_and_other_sweeps(golden_store):
    counting = CountingClient(golden_store.client)
    index = collect_runs(counting, EXPERIMENT, SWEEP, selections=False)
    assert counting.searches == 2  # the runs, then the cell runs deleted by hand (said in one line: issue 50)
    ids = golden_store.ids
    stale_twins = [f"personalized/lstm/mse/s{seed}" for seed in SEEDS]  # superseded by the newer stale runs
    assert {r.run_id for r in index.runs.values()} == {
        v for k, v in ids.items() if not k.endswith(("-old", "-failed")) and k not in stale_twins}
    assert {r.run_id for rs in index.duplicates.values() for r in rs} == {
        ids["personalized/lstm/ce/s0-old"], *(ids[k] for k in stale_twins)}


def test_collect_runs_errors_name_the_experiment_and_sweep(golden_store):
    with pytest.raises(BronchoError, match="experiment 'nope' not found"):
        collect_runs(golden_store.client, "nope", SWEEP)
    with pytest.raises(BronchoError, match="no runs of sweep 'nope'.*--sweep"):
        collect_runs(golden_store.client, EXPERIMENT, "nope")
