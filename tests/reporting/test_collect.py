"""Run collection: one query, latest FINISHED per cell, unfinished and duplicate bookkeeping, clear errors."""

from __future__ import annotations

import pytest
from report_fakes import EXPERIMENT, SWEEP

from bronchocli.errors import BronchoError
from bronchocli.reporting.collect import RunRecord, collect_runs, index_runs


def _rec(run_id: str, status: str = "FINISHED", start: int = 0, **tags: str) -> RunRecord:
    base = {"arch": "lstm", "rot_loss": "ce", "population": "personalized", "fold": "", "seed": "0",
            "pose_frame": "world"}
    return RunRecord(run_id, status, start, {**base, **tags}, {})


def test_latest_finished_run_wins_and_the_others_are_duplicates():
    index = index_runs([_rec("old", start=1), _rec("new", start=3), _rec("failed", "FAILED", start=9)], "s", "e")
    (ident, kept), = index.runs.items()
    assert kept.run_id == "new"
    assert [r.run_id for r in index.duplicates[ident]] == ["old"]
    assert index.unfinished == {}


def test_cells_with_only_unfinished_runs_are_remembered():
    index = index_runs([_rec("k", "KILLED"), _rec("f", "FAILED", arch="conv3d")], "s", "e")
    assert index.runs == {}
    assert sorted(r.run_id for rs in index.unfinished.values() for r in rs) == ["f", "k"]
    assert [r.run_id for r in index.not_finished("personalized", "conv3d", "ce")] == ["f"]


def test_mixed_pose_frames_need_a_choice():
    runs = [_rec("w"), _rec("c", pose_frame="camera")]
    with pytest.raises(BronchoError, match="several pose frames .*--pose-frame"):
        index_runs(runs, "s", "e")
    index = index_runs(runs, "s", "e", pose_frame="camera")
    assert [r.run_id for r in index.runs.values()] == ["c"] and index.pose_frame == "camera"


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


def test_collect_runs_makes_one_query_and_ignores_trials_and_other_sweeps(golden_store):
    client, _, ids = golden_store
    counting = CountingClient(client)
    index = collect_runs(counting, EXPERIMENT, SWEEP)
    assert counting.searches == 1
    kept = {r.run_id for r in index.runs.values()}
    assert kept == {v for k, v in ids.items() if not k.endswith(("-old", "-failed"))}
    assert {r.run_id for rs in index.duplicates.values() for r in rs} == {ids["personalized/lstm/ce-old"]}


def test_collect_runs_errors_name_the_experiment_and_sweep(golden_store):
    client, _, _ = golden_store
    with pytest.raises(BronchoError, match="experiment 'nope' not found"):
        collect_runs(client, "nope", SWEEP)
    with pytest.raises(BronchoError, match="no runs of sweep 'nope'.*--sweep"):
        collect_runs(client, EXPERIMENT, "nope")
